"""Automatic initial values for the elbow adjustment (seed 000, Section 2.2.2).

1. **The two connections.** The cloud's two extreme points (the point farthest from the centroid,
   then the point farthest from that one) lie on the rims of the two pipe ends. In case
   something else sticks out farther (a bracket's rod), two more pairs that avoid one of those
   points are tried as well, unless the first pair's start already fits the points closely
   (robust spread below ``QUIET``; for a flanged joint, whose sizes are rough until step 4's
   rotation refinement, judged after that refinement), and the candidate whose model fits the points best (trimmed
   mean squared distance) is kept. Steps 1-3 work on ``SLICE_SAMPLE`` random points of larger
   clouds (the adjustment then uses all of them).
2. **Slice cylinders.** Near each end a slice of points is cut and a cylinder fitted: the axis
   direction from the patch normals (the direction most perpendicular to all of them, normals by
   :func:`lrms.cylinder.estimate_normals`), the axis point and radius from an algebraic circle fit
   in the plane across it, then an orthogonal-distance polish with
   :func:`lrms.cylinder.refine_cylinder`. The slice is then re-cut as ``SLICE`` radii along the
   fitted axis from the end and the cylinder fitted again.
3. **Inner centre.** The two axes (nearly) intersect at the corner ``P`` of the elbow; the
   midpoint of their common perpendicular is taken. The bend plane's normal is the cross product
   of the two axis directions, and the angle between them gives the joint degree.
4. **Pose and size.** With the start leg along model ``+X`` the torus centre is
   ``O = P - A e_Z + A tan(d/2) e_X``. ``D`` is twice the mean slice radius; ``A`` is
   ``ratio D`` when the ratio is fixed, else found by golden-section search on the trimmed mean
   squared distance of the points to the model. The three rotations (about the model axes) are
   then refined one at a time by golden-section search on the same cost, twice over (the
   seed's golden-section search for ``Omega`` and ``Psi``).

5. **Global search** (when steps 1-4 fail, or their start leaves a robust residual spread of
   ``QUIET`` (4 %) of ``D`` or more: high noise, partial coverage). The slice cylinders need
   surface normals, which noise of 10 % of ``D`` destroys; the whole cloud still shows the bend.
   On a subsample of ``SEARCH_SAMPLE`` points: the bend plane is the cloud's best-fitting plane
   (PCA; isotropic noise leaves the eigenvectors alone), its normal the torus axis, and a
   diameter guess comes from the cloud's thickness across it (a whole tube has a standard
   deviation ``sqrt(r^2/2 + sigma^2)`` across its bend plane). A coarse grid over the start
   leg's direction in that plane (``KAPPA_STEPS``), the degree (given, or 45 and 90 deg, or the
   slice estimate), ``A/D`` (given, or 0.5, 1, 1.5) and ``D`` (``DIAMETER_FACTORS`` times the
   guess: a tube seen from one side is thinner) places the torus so that the arc's centroid is
   the cloud's centroid, and scores each by the soft-L1 cost of the orthogonal distances. The
   ``REFINE_TOP`` best and the slice start are refined by robust least squares
   (:func:`scipy.optimize.least_squares`, soft-L1 loss, every parameter free, ``A/D`` kept in
   [0.5, 5]) and ranked by the same cost; :func:`initial_candidates` returns up to three
   distinct ones, best first, and :func:`lrms.elbow.fit_auto` adjusts from each and keeps the
   lowest ``sigma0``.

Where it works (measured in ``bench/seed000_tables.py``, see ``docs/seed000-reproduction.md``):
Table 1's joints in any pose at 180 deg coverage or more, and at full coverage with noise up to
40 % of ``D``. A strip of 30 deg or less around the pipe does not fix the tube's axis and is
usually refused. :class:`lrms.errors.FitError` is raised when no elbow can be made out.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import replace

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from lrms.cylinder import Cylinder, CylinderModel, estimate_normals, refine_cylinder
from lrms.elbow.model import ElbowParams, as_points, evaluate_model
from lrms.errors import FitError
from lrms.ransac import ransac

FloatArray = NDArray[np.float64]

#: Slice length along the axis at each end, in tube radii (flanged joints: in flange radii).
SLICE = 0.8
FLANGE_SLICE = 0.35
#: Radius of the first patch around an end point, as a fraction of the end-to-end distance.
PATCH = 0.25
FLANGE_PATCH = 0.25
#: RANSAC inlier threshold for the slice cylinders, as a fraction of the end-to-end distance.
RANSAC_THRESHOLD = 0.015
#: Points used for the cost of the golden-section searches.
COST_SAMPLE = 4000
#: Tolerance (rad) of the golden-section searches on the rotation: 1 mrad turns a 0.1 m leg by
#: 0.1 mm, far inside what the adjustment starts from (the ``QUIET`` spread is 4 % of D).
ROTATION_TOL = 1e-3
#: Larger clouds are cut to this many random points for the slice cylinders (steps 1-4): the start
#: needs a few millimetres, not the full cloud's precision, which the adjustment on all points
#: brings (the slices' patches, RANSAC and polish then cost a fraction).
SLICE_SAMPLE = 10_000
#: The two ends' slice radii may differ by this factor at most (joints without flanges).
RADIUS_MISMATCH = 1.5
#: Fewest points for an automatic start.
MIN_POINTS = 200
#: Nominal degrees the estimated degree snaps to when within SNAP_DEG.
NOMINAL_DEGREES = (45.0, 90.0)
SNAP_DEG = 12.0
#: The slice start is used as it is when the robust spread of the points about it is below this
#: fraction of its D; otherwise the global search (step 5) runs too.
QUIET = 0.04
#: Points for the global search and the robust refinement.
SEARCH_SAMPLE = 1000
#: In-plane directions tried for the start leg (over the full turn).
KAPPA_STEPS = 24
#: Coarse candidates refined by robust least squares.
REFINE_TOP = 8
#: Function evaluations allowed to one robust refinement.
REFINE_NFEV = 60
#: Soft-L1 scale as a fraction of the diameter guessed from the cloud's thickness.
SOFT_SCALE = 0.1
#: Diameters tried by the global search, in units of the guess from the cloud's thickness.
DIAMETER_FACTORS = (1.0, 2.0, 3.5)
#: Flange diameter guessed for the global search, in D.
FLANGE_GUESS = 1.5


def _circle_fit(u: FloatArray, v: FloatArray) -> tuple[float, float, float]:
    """Algebraic (Kasa) circle fit: centre (u0, v0) and radius."""
    a = np.column_stack([u, v, np.ones_like(u)])
    b = u * u + v * v
    sol, *_ = np.linalg.lstsq(a, b, rcond=None)
    u0, v0 = sol[0] / 2, sol[1] / 2
    r2 = sol[2] + u0 * u0 + v0 * v0
    if not r2 > 0:
        raise FitError("slice circle fit failed (points not on a circle)")
    return float(u0), float(v0), math.sqrt(r2)


def _frame(w: FloatArray) -> tuple[FloatArray, FloatArray]:
    a = np.array([1.0, 0.0, 0.0]) if abs(w[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = np.cross(w, a)
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(w, e1)


def _slice_cylinder(
    patch: FloatArray, rng: np.random.Generator, size: float, radius_range: tuple[float, float] | None = None
) -> Cylinder:
    """Cylinder through a slice of pipe: RANSAC on points with normals, then an ODR polish.

    The RANSAC (:class:`lrms.cylinder.CylinderModel` in :func:`lrms.ransac.ransac`: axis from two
    points' normals) keeps the dominant cylinder of the patch, so a patch that also catches part
    of the bend or of a flange still gives the leg's cylinder.
    """
    if patch.shape[0] < 20:
        raise FitError(f"too few points near a pipe end for the slice cylinder ({patch.shape[0]})")
    sub = patch if patch.shape[0] <= 800 else patch[rng.choice(patch.shape[0], 800, replace=False)]
    normals = estimate_normals(sub, k=min(30, sub.shape[0]))
    thr = RANSAC_THRESHOLD * size
    model_class: type[CylinderModel] = CylinderModel
    if radius_range is not None:

        class _Ranged(CylinderModel):
            pass

        _Ranged.radius_range = radius_range
        model_class = _Ranged
    model: CylinderModel | None = None
    for attempt in range(3):  # noisier clouds need a wider threshold
        try:
            model, _ = ransac(
                np.hstack([sub, normals]),
                model_class,
                2,
                thr,
                max_trials=300,
                min_inliers=max(10, sub.shape[0] // 4),
                refine=False,
                rng=rng,
            )
            break
        except FitError as exc:
            if attempt == 2:
                raise FitError(f"no pipe found near an end of the cloud ({exc})") from exc
            thr *= 2.0
    assert model is not None and model.cylinder is not None
    cyl = model.cylinder
    near = np.abs(cyl.surface_distance(patch)) < thr
    if np.count_nonzero(near) < 20:
        return cyl
    try:
        return refine_cylinder(patch[near], cyl, sigma=None, max_rounds=2, gate=3.0).cylinder
    except FitError:
        return cyl


def _end_cylinder(
    pts: FloatArray,
    end: FloatArray,
    centroid: FloatArray,
    size: float,
    rng: np.random.Generator,
    flange: bool,
    cache: dict[tuple[float, ...], Cylinder] | None = None,
) -> Cylinder:
    """Cylinder fitted to the slice of points at one pipe end (memoized in ``cache`` by end point)."""
    key = tuple(float(x) for x in end)
    if cache is not None and key in cache:
        return cache[key]
    cyl = _end_cylinder_fit(pts, end, centroid, size, rng, flange)
    if cache is not None:
        cache[key] = cyl
    return cyl


def _end_cylinder_fit(
    pts: FloatArray,
    end: FloatArray,
    centroid: FloatArray,
    size: float,
    rng: np.random.Generator,
    flange: bool,
    radius_range: tuple[float, float] | None = None,
) -> Cylinder:
    patch = pts[np.linalg.norm(pts - end, axis=1) < (FLANGE_PATCH if flange else PATCH) * size]
    slice_len = FLANGE_SLICE if flange else SLICE
    cyl = _slice_cylinder(patch, rng, size, radius_range)
    for _ in range(2):
        w = cyl.direction if float((centroid - end) @ cyl.direction) > 0 else -cyl.direction
        t = (pts - cyl.point) @ w
        near = cyl.axis_distance(pts) < 1.6 * cyl.radius
        if np.count_nonzero(near) < 20:
            raise FitError("no pipe found near an end of the cloud")
        t0 = float(np.min(t[near]))
        sel = near & (t < t0 + slice_len * cyl.radius)
        cyl = _slice_cylinder(pts[sel], rng, size, radius_range)
    w = cyl.direction if float((centroid - end) @ cyl.direction) > 0 else -cyl.direction
    return Cylinder(cyl.point, w, cyl.radius)


def _trimmed_cost(pts: FloatArray, p: ElbowParams) -> float:
    ev = evaluate_model((pts - p.center) @ p.rot.T, p.A, p.D, p.degree, p.Df)
    cap = (0.25 * p.D) ** 2
    return float(np.mean(np.minimum(ev.f**2, cap)))


def _golden(fun: Callable[[float], float], lo: float, hi: float, tol: float = 1e-4) -> float:
    """Golden-section search for a minimum of ``fun`` on ``[lo, hi]`` (the seed's ref. 25).

    A bounded search rather than :func:`scipy.optimize.golden`, which needs a bracketing triple
    that a minimum on the interval's edge does not give.
    """
    invphi = (math.sqrt(5.0) - 1.0) / 2.0
    a, b = lo, hi
    c, d = b - invphi * (b - a), a + invphi * (b - a)
    fc, fd = fun(c), fun(d)
    while abs(b - a) > tol * max(1.0, abs(a) + abs(b)):
        if fc < fd:
            b, d, fd = d, c, fc
            c = b - invphi * (b - a)
            fc = fun(c)
        else:
            a, c, fc = c, d, fd
            d = a + invphi * (b - a)
            fd = fun(d)
    return 0.5 * (a + b)


def _sizes_from_pose(pts: FloatArray, p: ElbowParams, flange: bool) -> ElbowParams:
    """Tube (and flange) radius as the median distance of the points from the centre line."""
    ev = evaluate_model((pts - p.center) @ p.rot.T, p.A, p.D, p.degree, p.Df)
    bend = ev.portion == 1
    if flange:
        legs = ~bend
        d = 2 * float(np.median(ev.s[bend])) if np.count_nonzero(bend) > 20 else p.D
        df = 2 * float(np.median(ev.s[legs])) if np.count_nonzero(legs) > 20 else p.Df
        return replace(p, D=d, Df=df)
    return replace(p, D=2 * float(np.median(ev.s)))


def initial_values(
    points: ArrayLike,
    degree: float | None = None,
    ratio: float | None = None,
    flange: bool = False,
    rng: np.random.Generator | None = None,
) -> ElbowParams:
    """Initial elbow parameters from the cloud alone (see the module docstring).

    ``degree`` (rad) fixes the joint degree; ``None`` takes the angle between the two end axes
    (snapped to 45 or 90 deg when within 12 deg), or (global search) tries 45 and 90 deg.
    ``ratio`` fixes ``A = ratio D``. The best of :func:`initial_candidates`.
    """
    return initial_candidates(points, degree=degree, ratio=ratio, flange=flange, rng=rng)[0]


def initial_candidates(
    points: ArrayLike,
    degree: float | None = None,
    ratio: float | None = None,
    flange: bool = False,
    rng: np.random.Generator | None = None,
    max_candidates: int = 3,
    method: str = "auto",
) -> list[ElbowParams]:
    """Start values from the cloud alone, best first (at most ``max_candidates``, mutually distinct).

    The slice-cylinder start (steps 1-4 of the module docstring) is taken as it is when the
    points lie close to it (robust residual spread below ``QUIET`` of ``D``). Otherwise (high
    noise, partial coverage, or no usable slice) the global search of step 5 runs as well, and
    every start, the slice start included, is refined by robust least squares on a subsample and
    ranked by the same robust cost. ``method``: ``"auto"`` (as described), ``"slice"`` (the
    slice start only) or ``"global"`` (the global search only). Raises :class:`FitError` when
    neither yields an elbow.
    """
    if method not in ("auto", "slice", "global"):
        raise FitError(f"method must be 'auto', 'slice' or 'global', got {method!r}")
    pts = as_points(points)
    if pts.shape[0] < MIN_POINTS:
        raise FitError(f"too few points to find an elbow: {pts.shape[0]} (need at least {MIN_POINTS})")
    if not np.all(np.isfinite(pts)):
        raise FitError("points contain NaN or infinite coordinates")
    g = np.random.default_rng(12345) if rng is None else rng
    sample = pts if pts.shape[0] <= COST_SAMPLE else pts[g.choice(pts.shape[0], COST_SAMPLE, replace=False)]
    errors: list[str] = []
    slice_start: ElbowParams | None = None
    if method != "global":
        try:
            base = pts if pts.shape[0] <= SLICE_SAMPLE else pts[g.choice(pts.shape[0], SLICE_SAMPLE, replace=False)]
            slice_start = _slice_start(base, sample, degree, ratio, flange, g)
        except FitError as exc:
            if method == "slice":
                raise
            errors.append(f"slice cylinders: {exc}")
    if slice_start is not None and method == "slice":
        return [slice_start]
    if slice_start is not None and _robust_spread(sample, slice_start) < QUIET * slice_start.D:
        return [slice_start]
    small = (
        sample if sample.shape[0] <= SEARCH_SAMPLE else sample[g.choice(sample.shape[0], SEARCH_SAMPLE, replace=False)]
    )
    try:
        ranked = _global_search(small, degree, ratio, flange, [] if slice_start is None else [slice_start])
    except FitError as exc:
        errors.append(f"global search: {exc}")
        ranked = []
    if not ranked:
        raise FitError("no elbow found (" + "; ".join(errors) + ")")
    out: list[ElbowParams] = []
    for cand in ranked:
        if all(not _same_start(cand, o) for o in out):
            out.append(cand)
        if len(out) == max_candidates:
            break
    return out


def _slice_start(
    pts: FloatArray,
    sample: FloatArray,
    degree: float | None,
    ratio: float | None,
    flange: bool,
    g: np.random.Generator,
) -> ElbowParams:
    """Steps 1-4: slice cylinders at the two pipe ends, the corner, golden-section searches."""
    centroid = pts.mean(axis=0)
    best: ElbowParams | None = None
    best_cost = math.inf
    best_corner = centroid
    cache: dict[tuple[float, ...], Cylinder] = {}
    errors: list[str] = []
    refined_first = False
    first_turned: tuple[ElbowParams, ElbowParams] | None = None
    for e1, e2 in _end_candidates(pts, centroid):
        try:
            cand, corner = _from_ends(pts, sample, centroid, e1, e2, degree, ratio, flange, g, cache)
        except FitError as exc:
            errors.append(str(exc))
            continue
        cost = _trimmed_cost(sample, cand) / cand.D**2
        if cost < best_cost:
            best, best_cost, best_corner = cand, cost, corner
        if best is cand and _robust_spread(sample, cand) < QUIET * cand.D:
            # the pair fits the points closely already: the pairs that avoid one of its ends
            # (for something sticking out farther than a pipe end) cannot do better
            break
        if flange and best is cand and not refined_first:
            # a flanged start's sizes are rough until its rotation is refined (spread ~10 % of D
            # before, ~1 % after): judge the first pair after that refinement, which it gets anyway
            refined_first = True
            turned = _refine_rotation(sample, cand, corner, ratio, flange)
            if _robust_spread(sample, turned) < QUIET * turned.D:
                return turned
            first_turned = (cand, turned)  # kept: reused when this pair stays the best
    if best is None:
        raise FitError(errors[0] if errors else "no elbow found")
    if first_turned is not None and first_turned[0] is best:
        return first_turned[1]
    return _refine_rotation(sample, best, best_corner, ratio, flange)


def _residuals(pts: FloatArray, p: ElbowParams) -> FloatArray:
    return evaluate_model((pts - p.center) @ p.rot.T, p.A, p.D, p.degree, p.Df).f


def _robust_spread(pts: FloatArray, p: ElbowParams) -> float:
    """1.4826 times the median absolute orthogonal distance of ``pts`` to ``p``'s surface."""
    return 1.4826 * float(np.median(np.abs(_residuals(pts, p))))


def _same_start(a: ElbowParams, b: ElbowParams) -> bool:
    """Two starts that describe nearly the same surface (either labelling of the legs)."""
    if abs(a.degree - b.degree) > 1e-6:
        return False
    scale = max(a.D, b.D)
    for q in (b, b.flipped()):
        ang = float(np.linalg.norm(Rotation.from_matrix(a.rot @ q.rot.T).as_rotvec()))
        if ang < math.radians(5.0) and float(np.linalg.norm(a.center - q.center)) < 0.1 * scale:
            return True
    return False


def _global_search(
    small: FloatArray,
    degree: float | None,
    ratio: float | None,
    flange: bool,
    extra: list[ElbowParams],
) -> list[ElbowParams]:
    """Step 5: coarse search over the in-plane rotation, degree and A/D; robust refinement; ranking.

    The bend plane is the cloud's best-fitting plane (PCA: a tube bent in a plane is thinnest
    across it, and isotropic noise does not change the eigenvectors); its normal is the torus
    axis. For each in-plane direction of the start leg (``KAPPA_STEPS`` over the full turn; the
    model's mirror symmetry makes the other sign of the normal redundant), each degree (given, or
    45 and 90 deg) and each A/D (given, or 0.5, 1, 1.5) the torus centre is placed so that the
    bend's arc centroid falls on the cloud's centroid. The ``REFINE_TOP`` candidates of lowest
    robust cost, plus ``extra`` (the slice start), are refined by :func:`_robust_refine` and
    returned best first.
    """
    m = small.mean(axis=0)
    w, v = np.linalg.eigh(np.cov(small.T))
    n = v[:, 0]
    e1, e2 = v[:, 2], v[:, 1]
    d0 = 2.0 * math.sqrt(2.0 * max(float(w[0]), 1e-300))
    fs = SOFT_SCALE * d0
    degrees = [degree] if degree is not None else [math.radians(x) for x in NOMINAL_DEGREES]
    for p in extra:
        if degree is None and all(abs(p.degree - dd) > 1e-6 for dd in degrees):
            degrees.append(p.degree)
    ratios = [ratio] if ratio is not None else [0.5, 1.0, 1.5]
    # a tube seen from one side is thinner across the plane than a whole tube: larger guesses too
    dias = [f * d0 for f in DIAMETER_FACTORS] + [p.D for p in extra]
    cands: list[tuple[float, ElbowParams]] = []
    for k in range(KAPPA_STEPS):
        kap = 2.0 * math.pi * k / KAPPA_STEPS
        ex = math.cos(kap) * e1 + math.sin(kap) * e2
        ez = np.cross(ex, n)
        rot = np.vstack([ex, n, ez])
        for dg in degrees:
            b = math.pi / 2 + dg / 2
            ub = math.cos(b) * rot[0] + math.sin(b) * rot[2]
            for rt in ratios:
                for dia in dias:
                    a = rt * dia
                    rho = a * math.sin(dg / 2) / (dg / 2)
                    p = ElbowParams(m - rho * ub, rot, a, dia, dg, FLANGE_GUESS * dia if flange else None)
                    cands.append((_soft_cost(_residuals(small, p), fs), p))
    cands.sort(key=lambda t: t[0])
    refined: list[tuple[float, ElbowParams]] = []
    for p in [*extra, *(c[1] for c in cands[:REFINE_TOP])]:
        if flange and p.Df is None:
            p = replace(p, Df=FLANGE_GUESS * p.D)
        try:
            q = _robust_refine(small, p, ratio, flange, fs)
        except FitError:
            continue
        refined.append((_soft_cost(_residuals(small, q), fs), q))
    if not refined:
        raise FitError("the robust refinement failed from every start")
    refined.sort(key=lambda t: t[0])
    return [q for _, q in refined]


def _soft_cost(f: FloatArray, fs: float) -> float:
    """The soft-L1 cost of :func:`scipy.optimize.least_squares` (per point), scale ``fs``."""
    z = (f / fs) ** 2
    return float(np.mean(2.0 * (np.sqrt(1.0 + z) - 1.0)))


def _robust_refine(small: FloatArray, p: ElbowParams, ratio: float | None, flange: bool, fs: float) -> ElbowParams:
    """Robust least squares (soft L1, scale ``fs``) of all parameters from ``p`` on ``small``.

    Unknowns: the centre offset, a rotation vector applied to ``p.rot``, ``D``, and (ratio free)
    ``A/D`` bounded to [0.5, 5] so that the torus cannot cut itself, and ``Df/D`` for flanges.
    """
    d0 = p.D
    rot0 = p.rot

    def unpack(x: FloatArray) -> ElbowParams:
        rot = Rotation.from_rotvec(x[3:6]).as_matrix() @ rot0
        dia = d0 * float(x[6])
        a = (ratio if ratio is not None else float(x[7])) * dia
        df = dia * float(x[-1]) if flange else None
        return ElbowParams(p.center + d0 * x[:3], rot, a, dia, p.degree, df)

    x0 = [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0]
    lo = [-np.inf] * 6 + [0.05]
    hi = [np.inf] * 6 + [20.0]
    if ratio is None:
        x0.append(min(max(p.A / p.D, 0.5), 5.0))
        lo.append(0.5)
        hi.append(5.0)
    if flange:
        x0.append(min(max((p.Df or FLANGE_GUESS * p.D) / p.D, 1.0), 4.0))
        lo.append(1.0)
        hi.append(4.0)

    def fun(x: FloatArray) -> FloatArray:
        return _residuals(small, unpack(x)) / d0

    try:
        res = least_squares(
            fun, np.array(x0), bounds=(lo, hi), loss="soft_l1", f_scale=fs / d0, max_nfev=REFINE_NFEV, x_scale=1.0
        )
    except ValueError as exc:  # non-finite residuals
        raise FitError(f"robust refinement failed: {exc}") from exc
    return unpack(np.asarray(res.x))


def _end_candidates(pts: FloatArray, centroid: FloatArray) -> list[tuple[FloatArray, FloatArray]]:
    """Pairs of points that may be the two pipe ends: the farthest pair found from the centroid,
    and pairs that avoid one of its points (in case something else, e.g. a bracket, sticks out)."""

    def far(ref: FloatArray, mask: NDArray[np.bool_] | None = None) -> FloatArray:
        d = np.linalg.norm(pts - ref, axis=1)
        if mask is not None:
            d = np.where(mask, d, -1.0)
        return np.asarray(pts[int(np.argmax(d))])

    e1 = far(centroid)
    e2 = far(e1)
    size = float(np.linalg.norm(e2 - e1))
    if size <= 0:
        raise FitError("all points coincide")
    out = [(e1, e2)]
    for drop, keep in ((e1, e2), (e2, e1)):
        mask = np.linalg.norm(pts - drop, axis=1) > 0.4 * size
        if np.count_nonzero(mask) > 0.5 * pts.shape[0]:
            e3 = far(keep, mask)
            out.append((keep, e3))
    return out


def _from_ends(
    pts: FloatArray,
    sample: FloatArray,
    centroid: FloatArray,
    e1: FloatArray,
    e2: FloatArray,
    degree: float | None,
    ratio: float | None,
    flange: bool,
    g: np.random.Generator,
    cache: dict[tuple[float, ...], Cylinder],
) -> tuple[ElbowParams, FloatArray]:
    """Initial values from two given end points (steps 2-4 of the module docstring, without the
    rotation refinement) and the corner point."""
    size = float(np.linalg.norm(e2 - e1))
    c1 = _end_cylinder(pts, e1, centroid, size, g, flange, cache)
    c2 = _end_cylinder(pts, e2, centroid, size, g, flange, cache)
    r_lo, r_hi = sorted((c1.radius, c2.radius))
    if not flange and r_hi > RADIUS_MISMATCH * r_lo:
        # one slice went wrong, most likely the larger (a flat-looking patch): fit it again with
        # the other's radius (+-30 %); failing that, the other way round
        order = ((1, 2), (2, 1)) if c1.radius > c2.radius else ((2, 1), (1, 2))
        for bad, good in order:
            ref = (c1, c2)[good - 1].radius
            try:
                redo = _end_cylinder_fit(pts, (e1, e2)[bad - 1], centroid, size, g, flange, (0.7 * ref, 1.3 * ref))
            except FitError:
                continue
            if bad == 1:
                c1 = redo
            else:
                c2 = redo
            break
        r_lo, r_hi = sorted((c1.radius, c2.radius))
    if 2 * r_hi > size or (not flange and r_hi > RADIUS_MISMATCH * r_lo):
        raise FitError(
            f"no elbow found: the pipe ends give radii {c1.radius * 1e3:.0f} and {c2.radius * 1e3:.0f} mm "
            f"for a cloud {size * 1e3:.0f} mm across"
        )
    u1, u2 = c1.direction, c2.direction
    normal = np.cross(u1, u2)
    sn = float(np.linalg.norm(normal))
    d_est = math.acos(float(np.clip(-u1 @ u2, -1.0, 1.0)))
    if sn < math.sin(math.radians(10.0)) or d_est < math.radians(10.0):
        raise FitError(f"no elbow found: the two pipe ends are nearly parallel (turn {math.degrees(d_est):.1f} deg)")
    if degree is None:
        deg = math.degrees(d_est)
        near = [nd for nd in NOMINAL_DEGREES if abs(nd - deg) <= SNAP_DEG]
        degree = math.radians(near[0]) if near else d_est
    # corner: midpoint of the common perpendicular of the two axes
    r12 = c1.point - c2.point
    b = float(u1 @ u2)
    den = 1.0 - b * b
    s = (b * float(u2 @ r12) - float(u1 @ r12)) / den
    t = (float(u2 @ r12) - b * float(u1 @ r12)) / den
    corner = 0.5 * ((c1.point + s * u1) + (c2.point + t * u2))
    ex = -u1
    ey = normal / sn
    ez = np.cross(ex, ey)
    rot = np.vstack([ex, ey, ez])
    dia = c1.radius + c2.radius
    df: float | None = None
    if flange:
        df = dia
    a0 = dia if ratio is None else ratio * dia

    def params_for(a: float, rot_: FloatArray = rot) -> ElbowParams:
        o = corner - a * rot_[2] + a * math.tan(degree / 2) * rot_[0]
        return ElbowParams(o, rot_, a, dia, float(degree), df)

    p = params_for(a0)
    if flange:
        # the slices measured the flanges: D and Df from the pose, then A from the tube's D
        p = _sizes_from_pose(sample, p, True)
        if ratio is not None:
            p = replace(params_for(ratio * p.D), D=p.D, Df=p.Df)
            p = _sizes_from_pose(sample, p, True)
            p = replace(params_for(ratio * p.D), D=p.D, Df=p.Df)
    if ratio is None:
        a_best = _golden(lambda a: _trimmed_cost(sample, replace(params_for(a), D=p.D, Df=p.Df)), 0.5 * p.D, 2.0 * p.D)
        p = replace(params_for(max(a_best, 0.45 * p.D)), D=p.D, Df=p.Df)
    return p, corner


def _refine_rotation(
    sample: FloatArray, p: ElbowParams, corner: FloatArray, ratio: float | None, flange: bool
) -> ElbowParams:
    """Golden-section refinement of the rotation about each model axis (pivot: the corner)."""
    for _ in range(2):
        for axis in range(3):

            def cost(angle: float, axis: int = axis, base: ElbowParams = p) -> float:
                return _trimmed_cost(sample, _rotated(base, axis, angle, corner, ratio))

            best = _golden(cost, -0.15, 0.15, tol=ROTATION_TOL)
            p = _rotated(p, axis, best, corner, ratio)
        p = _sizes_from_pose(sample, p, flange)
        if ratio is not None:
            p = replace(p, A=ratio * p.D)
    return p


def _rotated(p: ElbowParams, axis: int, angle: float, pivot: FloatArray, ratio: float | None) -> ElbowParams:
    """``p`` turned by ``angle`` about model axis ``axis`` through ``pivot`` (world point)."""
    rv = np.zeros(3)
    rv[axis] = angle
    dr = Rotation.from_rotvec(rv).as_matrix()
    rot = dr @ p.rot
    # the centre turns with the frame about the pivot
    center = pivot + rot.T @ (p.rot @ (p.center - pivot))
    return replace(p, rot=rot, center=center)
