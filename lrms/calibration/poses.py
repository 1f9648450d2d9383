"""Sweeps from several rig poses: registering each sweep's surfaces to the first sweep's frame.

Each sweep is detected on its own (planes, spheres) in its own nominal cloud. A sweep after the
first is placed by the reference spheres it shares with the first: every triple of its spheres
is tried against every triple of the first sweep's (equal diameters, centre distances within
``tolerance_m``), the rigid transform of each consistent pair of triples (Kabsch) is applied to
all its spheres, and the transform under which most spheres land on a sphere of the same
diameter (least rms on a tie) is the sweep's initial pose; its spheres take the identities of
the first sweep's they land on; a sphere of an artefact index no earlier sweep found joins the
world's spheres, placed by the sweep's initial pose (a far sphere lost in the first sweep's nominal
cloud is still used: docs/calibration.md, "A lost far sphere"), unless it could be a second copy
of a world sphere (:func:`_may_join`): its index can be a guess (spheres of equal diameter the
centre distances did not tell apart go in the found order), so its place is checked instead. Its planes
are then moved into the world and merged with a world plane of the same orientation (within
``angle_deg``) and offset (within ``tolerance_m`` x 2), or added as a new one. The adjustment
(:class:`lrms.calibration.adjust.Adjustment` with ``which`` and ``poses``) refines the poses with
the rig.
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

from lrms.calibration.data import Artefact, CalibrationError
from lrms.calibration.detect import PlaneSeg, SphereSeg

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]


class RegistrationError(CalibrationError):
    """A sweep could not be placed relative to the first (too few common spheres)."""


#: Growth of the registration tolerance per metre of distance (:func:`match_spheres`'s default).
RANGE_TOLERANCE = 0.01


def kabsch(a: FloatArray, b: FloatArray) -> FloatArray:
    """The proper rigid transform (4x4) taking points ``a`` (N, 3) onto ``b`` in least squares."""
    ca, cb = a.mean(axis=0), b.mean(axis=0)
    u, _, vt = np.linalg.svd((a - ca).T @ (b - cb))
    s = np.diag([1.0, 1.0, float(np.sign(np.linalg.det(vt.T @ u.T)))])
    rot = vt.T @ s @ u.T
    t = np.eye(4)
    t[:3, :3] = rot
    t[:3, 3] = cb - rot @ ca
    return t


def match_spheres(
    ref: Sequence[SphereSeg],
    other: Sequence[SphereSeg],
    tolerance_m: float = 0.1,
    min_spread_m: float = 0.1,
    range_tolerance: float = RANGE_TOLERANCE,
) -> tuple[FloatArray, dict[int, int]]:
    """The initial pose (4x4, ``other``'s frame into ``ref``'s) and the matches ``{other position:
    ref position}``. Raises :class:`RegistrationError` without three common spheres off a line.
    The tolerances grow by ``range_tolerance`` per metre of the centre distance compared (of the
    first sweep's centre's range, for a sphere landing on it): the nominal clouds are distorted in
    proportion to range (:attr:`lrms.calibration.detect.DetectOptions.range_tolerance`)."""
    rc = np.array([s.center for s in ref])
    oc = np.array([s.center for s in other])
    rr = np.array([s.radius for s in ref])
    orad = np.array([s.radius for s in other])
    ref_range = np.linalg.norm(rc, axis=1)
    best: tuple[int, float, FloatArray, dict[int, int]] | None = None
    for tri in itertools.combinations(range(len(ref)), 3):
        ti = np.array(tri)
        if np.linalg.svd(rc[ti] - rc[ti].mean(axis=0), compute_uv=False)[1] < min_spread_m:
            continue  # three centres on a line do not fix a rotation
        d_ref = np.linalg.norm(rc[ti][:, None] - rc[ti][None], axis=2)
        for perm in itertools.permutations(range(len(other)), 3):
            pi = np.array(perm)
            if np.any(np.abs(orad[pi] - rr[ti]) > 1e-9):
                continue
            d_other = np.linalg.norm(oc[pi][:, None] - oc[pi][None], axis=2)
            if np.any(np.abs(d_other - d_ref) > tolerance_m + range_tolerance * d_ref):
                continue
            t = kabsch(oc[pi], rc[ti])
            moved = oc @ t[:3, :3].T + t[:3, 3]
            dist = np.linalg.norm(moved[:, None] - rc[None], axis=2)
            dist[np.abs(orad[:, None] - rr[None]) > 1e-9] = np.inf
            pairs: dict[int, int] = {}
            err = []
            for i in np.argsort(dist.min(axis=1)):
                j = int(np.argmin(dist[i]))
                if dist[i, j] <= tolerance_m + range_tolerance * ref_range[j] and j not in pairs.values():
                    pairs[int(i)] = j
                    err.append(dist[i, j])
            rms = float(np.sqrt(np.mean(np.square(err))))
            if best is None or len(pairs) > best[0] or (len(pairs) == best[0] and rms < best[1]):
                best = (len(pairs), rms, t, pairs)
    if best is None:
        raise RegistrationError(
            f"no three reference spheres off a line seen in both sweeps agree within {tolerance_m} m "
            f"+ {range_tolerance} m per m "
            f"({len(ref)} and {len(other)} spheres found): separate poses need at least three common spheres"
        )
    _, _, t, pairs = best
    # refine on all matched spheres
    oi = np.array(list(pairs))
    t = kabsch(oc[oi], rc[np.array([pairs[i] for i in oi])])
    return t, pairs


def _may_join(
    world: Sequence[SphereSeg],
    new: SphereSeg,
    artefact: Artefact | None,
    tolerance_m: float,
    range_tolerance: float = RANGE_TOLERANCE,
) -> bool:
    """Whether ``new`` (a later sweep's sphere no world sphere matched, its centre in the world
    frame) may join the ``world`` spheres as another physical sphere.

    Its artefact index can be a guess (:func:`lrms.calibration.detect._assign_pairwise` gives
    spheres of equal diameter that no distance told apart in the found order), so it is checked by
    place: it must not overlap a world sphere (two spheres' centres are at least the sum of their
    radii apart; one nearer is the same sphere seen again, off by the initial pose); with the
    ``artefact``, its index one of the artefact's spheres of its diameter and every artefact
    distance from its index to a world sphere's index met within ``tolerance_m`` plus
    ``range_tolerance`` per metre."""
    for w in world:
        if float(np.linalg.norm(w.center - new.center)) < w.radius + new.radius:
            return False
    if artefact is None:
        return True
    same = [k for k, sp in enumerate(artefact.spheres) if np.isclose(sp.diameter_m, 2 * new.radius)]
    if new.artefact_index not in same:
        return False
    at = {w.artefact_index: w for w in world}
    for d in artefact.distances:
        if new.artefact_index not in (d.a, d.b):
            continue
        other = at.get(d.b if d.a == new.artefact_index else d.a)
        if other is None:
            continue
        err = abs(float(np.linalg.norm(other.center - new.center)) - d.distance_m)
        if err > tolerance_m + range_tolerance * d.distance_m:
            return False
    return True


def merge(
    planes: Sequence[Sequence[PlaneSeg]],
    spheres: Sequence[Sequence[SphereSeg]],
    offsets: Sequence[int],
    tolerance_m: float = 0.1,
    angle_deg: float = 5.0,
    artefact: Artefact | None = None,
) -> tuple[list[PlaneSeg], list[SphereSeg], list[FloatArray]]:
    """World surfaces (beam indices into the concatenated sweeps, ``offsets`` = each sweep's first
    beam) and each sweep's initial pose, from the surfaces detected per sweep (see the module
    docstring). ``artefact``: the spheres' diameters and distances, which a sphere joining from a
    later sweep must agree with (:func:`_may_join`; without it, only its place is checked)."""
    poses = [np.eye(4)]
    ref = list(spheres[0])
    members: dict[int, list[IntArray]] = {k: [s.index + offsets[0]] for k, s in enumerate(ref)}
    for k in range(1, len(spheres)):
        try:
            t, pairs = match_spheres(ref, spheres[k], tolerance_m)
        except RegistrationError as exc:
            raise RegistrationError(f"sweep {k + 1}: {exc}") from None
        poses.append(t)
        for i, j in pairs.items():
            members[j].append(spheres[k][i].index + offsets[k])
        # a sphere this sweep found and no earlier one did (e.g. one far out on the first pose's
        # shaft, lost in its nominal cloud: docs/calibration.md, "A lost far sphere") joins the
        # world's, placed by this sweep's initial pose, if it cannot be a copy of a world sphere
        known = {s.artefact_index for s in ref}
        for i, sp in enumerate(spheres[k]):
            if i in pairs or sp.artefact_index in known:
                continue
            moved = SphereSeg(sp.index, t[:3, :3] @ sp.center + t[:3, 3], sp.radius, sp.artefact_index)
            if _may_join(ref, moved, artefact, tolerance_m):
                members[len(ref)] = [sp.index + offsets[k]]
                ref.append(moved)
                known.add(sp.artefact_index)
    world_spheres = [
        SphereSeg(np.concatenate(members[j]), s.center, s.radius, s.artefact_index) for j, s in enumerate(ref)
    ]
    world_planes: list[tuple[FloatArray, float, list[IntArray]]] = []
    cos_tol = np.cos(np.deg2rad(angle_deg))
    for k, sweep_planes in enumerate(planes):
        rot, tr = poses[k][:3, :3], poses[k][:3, 3]
        for pl in sweep_planes:
            n = rot @ pl.normal
            d = pl.offset + float(n @ tr)
            for wn, wd, idx in world_planes:
                if float(n @ wn) >= cos_tol and abs(d - wd) <= 2 * tolerance_m:
                    idx.append(pl.index + offsets[k])
                    break
                if float(n @ wn) <= -cos_tol and abs(d + wd) <= 2 * tolerance_m:
                    idx.append(pl.index + offsets[k])
                    break
            else:
                world_planes.append((n, d, [pl.index + offsets[k]]))
    out = [PlaneSeg(np.sort(np.concatenate(idx)), n, d) for n, d, idx in world_planes]
    return out, world_spheres, poses
