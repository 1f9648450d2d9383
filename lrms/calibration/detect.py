"""Finding the calibration surfaces in a cloud mapped with the nominal rig: planes, then spheres.

Planes: sequential RANSAC (:func:`lrms.ransac.ransac` with :class:`~lrms.ransac.PlaneModel`)
with a loose threshold (a miscalibrated rig bends a wall by up to a few centimetres), largest
first, until the next plane holds fewer than ``min_plane_points``; a plane whose points spread
less than ``min_plane_extent_m`` (standard deviation along its second axis, of its main patch), or
whose points do not form one connected patch for the most part (neighbours within ``plane_gap_m``:
the caps of spheres that happen to line up, strips of bent walls), is not taken. Spheres: the points that are
on no plane are split into connected clusters (neighbours within ``cluster_gap_m``), a sphere
is fitted to each cluster (algebraic, then geometric least squares), and a cluster is taken as
the artefact's sphere whose radius is nearest, if the fitted radius is within
``radius_tolerance`` of it and the fit is tight. Spheres of equal diameter are told apart by the
artefact's centre distances where given.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy import optimize, sparse
from scipy.sparse import csgraph
from scipy.spatial import cKDTree

from lrms.calibration.data import Artefact, DetectionError
from lrms.errors import FitError
from lrms.ransac import PlaneModel, ransac

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]


@dataclass(frozen=True)
class DetectOptions:
    plane_threshold_m: float = 0.06
    min_plane_points: int = 2000
    max_planes: int = 12
    min_plane_extent_m: float = 0.25
    plane_gap_m: float = 0.25
    cluster_gap_m: float = 0.05
    min_sphere_points: int = 40
    radius_tolerance_m: float = 0.03
    sphere_threshold_m: float = 0.05
    distance_tolerance_m: float = 0.05
    #: the sphere tests' tolerances grow by this much per metre of the sphere's range (and the
    #: distance match's per metre of distance): in the nominal cloud, angle errors up to 0.3 deg
    #: each (alpha zero, the scan plane's tilt) smear and move a sphere 5 mm per metre of range,
    #: 47 mm at 9 m (docs/calibration.md, "The hall layout (k1)")
    range_tolerance: float = 0.01
    seed: int = 0


@dataclass(frozen=True)
class PlaneSeg:
    index: IntArray
    normal: FloatArray
    offset: float


@dataclass(frozen=True)
class SphereSeg:
    index: IntArray
    center: FloatArray
    radius: float
    artefact_index: int


def detect_planes(points: FloatArray, opts: DetectOptions, rng: np.random.Generator) -> list[PlaneSeg]:
    """Planes of the room, largest first (indices into ``points``); each point on at most one."""
    n = points.shape[0]
    free = np.ones(n, dtype=bool)
    planes: list[PlaneSeg] = []
    while len(planes) < opts.max_planes and int(free.sum()) >= opts.min_plane_points:
        idx = np.flatnonzero(free)
        try:
            model, mask = ransac(
                points[idx],
                PlaneModel,
                3,
                opts.plane_threshold_m,
                max_trials=400,
                min_inliers=opts.min_plane_points,
                score_size=20000,
                rng=rng,
            )
        except FitError:
            break
        members = idx[mask]
        free[members] = False
        if plane_support_ok(points, members, opts, rng):
            planes.append(PlaneSeg(members, model.normal.copy(), float(model.offset)))
    return planes


def plane_support_ok(points: FloatArray, members: IntArray, opts: DetectOptions, rng: np.random.Generator) -> bool:
    """Whether ``points[members]`` can be a plane of the room: at least ``min_plane_points``, for
    the most part one connected patch (neighbours within ``plane_gap_m``, in a random subset of
    4,000: caps of spheres that happen to line up, strips of other walls are not), and that main
    patch spread at least ``min_plane_extent_m`` (standard deviation along its second axis: a
    slice through a sphere, or one sphere's cap with a few leftovers of the walls far off for
    spread, is not a plane; docs/calibration.md, "A lost far sphere")."""
    if members.size < opts.min_plane_points:
        return False
    main = _main_patch(points[members], opts.plane_gap_m, rng)
    if main is None:
        return False
    sv = np.linalg.svd(main - main.mean(axis=0), compute_uv=False)
    return bool(sv[1] / np.sqrt(main.shape[0]) >= opts.min_plane_extent_m)


def _main_patch(pts: FloatArray, gap: float, rng: np.random.Generator, sample: int = 4000) -> FloatArray | None:
    """The largest connected patch (neighbours within ``gap``) of a random subset of ``sample`` of
    a plane's points, or ``None`` when it holds less than half of them."""
    if pts.shape[0] > sample:
        pts = pts[rng.choice(pts.shape[0], sample, replace=False)]
    pairs = cKDTree(pts).query_pairs(gap, output_type="ndarray")
    graph = sparse.coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(len(pts), len(pts)))
    _, labels = csgraph.connected_components(graph, directed=False)
    counts = np.bincount(labels)
    if counts.max() < 0.5 * len(pts):
        return None
    return np.asarray(pts[labels == counts.argmax()])


def _fit_sphere(pts: FloatArray) -> tuple[FloatArray, float, float]:
    """Centre, radius and rms of a least-squares sphere (algebraic start, geometric refinement)."""
    a = np.column_stack([2 * pts, np.ones(len(pts))])
    sol, *_ = np.linalg.lstsq(a, np.einsum("ij,ij->i", pts, pts), rcond=None)
    c0 = sol[:3]
    r0 = float(np.sqrt(max(sol[3] + c0 @ c0, 1e-12)))

    def res(x: FloatArray) -> FloatArray:
        return np.asarray(np.linalg.norm(pts - x[:3], axis=1) - x[3], dtype=np.float64)

    fit = optimize.least_squares(res, np.r_[c0, r0], method="lm")
    r = fit.fun
    return fit.x[:3], float(abs(fit.x[3])), float(np.sqrt(np.mean(r * r)))


def _fit_sphere_known(pts: FloatArray, center: FloatArray, radius: float) -> tuple[FloatArray, float]:
    def res(c: FloatArray) -> FloatArray:
        return np.asarray(np.linalg.norm(pts - c, axis=1) - radius, dtype=np.float64)

    fit = optimize.least_squares(res, center, method="lm")
    return fit.x, float(np.sqrt(np.mean(fit.fun**2)))


def detect_spheres(
    points: FloatArray, candidates: IntArray, artefact: Artefact, opts: DetectOptions
) -> list[SphereSeg]:
    """The artefact's spheres among ``points[candidates]`` (the points on no plane)."""
    if not artefact.spheres:
        return []
    if candidates.size == 0:
        raise DetectionError(
            f"no spheres found: every point lies on a plane (the artefact has {len(artefact.spheres)})"
        )
    pts = points[candidates]
    tree = cKDTree(pts)
    pairs = tree.query_pairs(opts.cluster_gap_m, output_type="ndarray")
    graph = sparse.coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(len(pts), len(pts)))
    n_comp, labels = csgraph.connected_components(graph, directed=False)
    counts = np.bincount(labels, minlength=n_comp)
    radii = np.array([s.diameter_m / 2 for s in artefact.spheres])
    found: list[tuple[IntArray, FloatArray, float, float]] = []  # index, centre, radius, rms
    for comp in np.flatnonzero(counts >= opts.min_sphere_points):
        members = np.flatnonzero(labels == comp)
        c, r, _ = _fit_sphere(pts[members])
        slack = opts.range_tolerance * float(np.linalg.norm(c))
        k = int(np.argmin(np.abs(radii - r)))
        if abs(radii[k] - r) > opts.radius_tolerance_m + slack:
            continue
        c, rms = _fit_sphere_known(pts[members], c, float(radii[k]))
        if rms > opts.sphere_threshold_m / 2 + slack:
            continue
        dist = np.abs(np.linalg.norm(pts[members] - c, axis=1) - radii[k])
        found.append((candidates[members[dist < opts.sphere_threshold_m + slack]], c, float(radii[k]), rms))
    if not found:
        raise DetectionError(
            f"no spheres found: no cluster of >= {opts.min_sphere_points} points off the planes fits a sphere of "
            f"diameter {', '.join(f'{2 * r:.4g}' for r in sorted(set(radii)))} m within {opts.radius_tolerance_m} m"
        )
    return _assign(found, artefact, opts)


def detect_surfaces(
    points: FloatArray, artefact: Artefact, opts: DetectOptions, rng: np.random.Generator
) -> tuple[list[PlaneSeg], list[SphereSeg]]:
    """Planes (when ``artefact.planes``) and the artefact's spheres in ``points`` (the rig at the origin).

    A plane's points that lie on a found sphere's surface (within ``sphere_threshold_m``, on the
    side facing the rig) are the sphere's, not the plane's: they are taken off the plane, and a
    plane whose remaining support no longer passes :func:`plane_support_ok` (too few points, too
    small, not one patch) is dropped: a slab of the loose RANSAC threshold through a sphere's cap,
    with a few leftovers of the walls for extent, is no plane of the room. The spheres are then
    found again among the points on no plane, until no plane changes (docs/calibration.md,
    "Spurious planes on the spheres")."""
    planes = detect_planes(points, opts, rng) if artefact.planes else []
    if artefact.planes and not planes:
        raise DetectionError(f"no planes found (none with >= {opts.min_plane_points} points)")
    spheres = detect_spheres(points, _off(planes, len(points)), artefact, opts)
    for _ in range(len(planes)):
        kept: list[PlaneSeg] = []
        for pl in planes:
            on = np.zeros(pl.index.size, dtype=bool)
            x = points[pl.index]
            for sp in spheres:
                rel = x - sp.center
                on |= (np.abs(np.linalg.norm(rel, axis=1) - sp.radius) < opts.sphere_threshold_m) & (
                    np.einsum("ij,ij->i", rel, x) < 0
                )  # on the shell's side facing the rig (its back is hidden: a wall there is no sphere's)
            if not on.any():
                kept.append(pl)
            elif plane_support_ok(points, pl.index[~on], opts, rng):
                kept.append(PlaneSeg(pl.index[~on], pl.normal, pl.offset))
        if len(kept) == len(planes) and all(a.index.size == b.index.size for a, b in zip(kept, planes, strict=True)):
            break
        planes = kept
        if artefact.planes and not planes:
            raise DetectionError("no planes found: every plane found lies on the spheres")
        spheres = detect_spheres(points, _off(planes, len(points)), artefact, opts)
    return planes, spheres


def _off(planes: list[PlaneSeg], n: int) -> IntArray:
    """The indices of ``n`` points on none of ``planes``."""
    on_plane = np.zeros(n, dtype=bool)
    for pl in planes:
        on_plane[pl.index] = True
    return np.flatnonzero(~on_plane)


#: The most joint assignments of found to artefact spheres :func:`_assign` tries before it falls
#: back to matching one distance at a time (7 spheres of one diameter: 5040).
MAX_ASSIGNMENTS = 50_000


def _assign(
    found: list[tuple[IntArray, FloatArray, float, float]], artefact: Artefact, opts: DetectOptions
) -> list[SphereSeg]:
    """Give each found sphere an artefact sphere of its diameter; the centre distances decide
    between spheres of equal diameter.

    Every assignment (found spheres of one diameter to the artefact's of that diameter, all
    groups jointly; at most :data:`MAX_ASSIGNMENTS`) is scored by its distances: each given
    distance costs its misfit, capped at ``distance_tolerance_m``, or that cap when one of its
    spheres is unassigned. The cheapest is taken (ties: the found order). So a sphere network
    (many distances sharing spheres) is matched as a whole, not pair by pair.
    """
    diam = np.array([s.diameter_m for s in artefact.spheres])
    groups: list[tuple[list[int], list[int]]] = []  # (artefact indices, found indices) per diameter
    for k in range(len(diam)):
        if any(k in g[0] for g in groups):
            continue
        art = [j for j in range(len(diam)) if np.isclose(diam[j], diam[k])]
        fnd = [i for i, f in enumerate(found) if np.isclose(2 * f[2], diam[k])]
        groups.append((art, fnd))
    n_total = 1
    for art, fnd in groups:
        hi, lo = max(len(art), len(fnd)), min(len(art), len(fnd))
        n_total *= int(np.prod(np.arange(hi - lo + 1, hi + 1)))
    if n_total > MAX_ASSIGNMENTS or not artefact.distances:
        return _assign_pairwise(found, artefact, opts)
    tol = opts.distance_tolerance_m
    centres = np.array([f[1] for f in found])
    best: tuple[float, dict[int, int]] | None = None
    per_group = [
        [dict(zip(perm, fnd, strict=True)) for perm in itertools.permutations(art, len(fnd))]
        if len(fnd) <= len(art)
        else [dict(zip(art, perm, strict=True)) for perm in itertools.permutations(fnd, len(art))]
        for art, fnd in groups
    ]
    for combo in itertools.product(*per_group):
        owner = {a: f for part in combo for a, f in part.items()}
        cost = 0.0
        for d in artefact.distances:
            if d.a in owner and d.b in owner:
                err = abs(float(np.linalg.norm(centres[owner[d.a]] - centres[owner[d.b]])) - d.distance_m)
                cost += min(err, tol + opts.range_tolerance * d.distance_m)
            else:
                cost += tol + opts.range_tolerance * d.distance_m
        if best is None or cost < best[0] - 1e-12:
            best = (cost, owner)
    assert best is not None
    return [SphereSeg(found[i][0], found[i][1], found[i][2], k) for k, i in sorted(best[1].items())]


def _assign_pairwise(
    found: list[tuple[IntArray, FloatArray, float, float]], artefact: Artefact, opts: DetectOptions
) -> list[SphereSeg]:
    """Too many spheres for :func:`_assign`'s joint search: each distance, one at a time, takes the
    pair of found spheres that matches it best; the rest go in the found order."""
    diam = np.array([s.diameter_m for s in artefact.spheres])
    owner: dict[int, int] = {}  # artefact index -> found index
    used: set[int] = set()
    for d in artefact.distances:
        best: tuple[float, int, int] | None = None
        for i, fi in enumerate(found):
            for j, fj in enumerate(found):
                if i == j or i in used or j in used:
                    continue
                if not (np.isclose(2 * fi[2], diam[d.a]) and np.isclose(2 * fj[2], diam[d.b])):
                    continue
                err = abs(float(np.linalg.norm(fi[1] - fj[1])) - d.distance_m)
                if err < opts.distance_tolerance_m + opts.range_tolerance * d.distance_m and (
                    best is None or err < best[0]
                ):
                    best = (err, i, j)
        if best is not None and d.a not in owner and d.b not in owner:
            owner[d.a], owner[d.b] = best[1], best[2]
            used.update((best[1], best[2]))
    for i, f in enumerate(found):
        if i in used:
            continue
        free = [k for k in range(len(diam)) if k not in owner and np.isclose(diam[k], 2 * f[2])]
        if free:
            owner[free[0]] = i
            used.add(i)
    return [SphereSeg(found[i][0], found[i][1], found[i][2], k) for k, i in sorted(owner.items())]
