"""Rig calibration (issue 12): the rig's geometry and the scanner's range errors from sweeps of a
room and reference spheres, by adjustment on the raw observations.

Typical use::

    from lrms.calibration import Artefact, Observations, calibrate
    result = calibrate([Observations.from_points(cloud)], Artefact.from_dict(json.load(f)))
    result.model          # the estimated RigModel (lrms.kinematics)
    result.to_json()      # values, covariance, correlations, residuals, identifiability report

See docs/calibration.md for the model, the artefacts and the identifiability rules.
"""

from __future__ import annotations

import datetime
import logging
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

import lrms
from lrms.calibration.adjust import (
    GOAL,
    SPREAD,
    STRUCTURAL,
    Adjustment,
    AdjustOptions,
    resegment_settled,
)
from lrms.calibration.data import (
    Artefact,
    ArtefactError,
    CalibrationError,
    CloudTooSmallError,
    DetectionError,
    DistanceSpec,
    Observations,
    SphereSpec,
    concatenate,
)
from lrms.calibration.detect import DetectOptions, PlaneSeg, SphereSeg, detect_surfaces
from lrms.calibration.optics import SpotScale, estimate_spot_scale
from lrms.calibration.poses import RegistrationError, merge
from lrms.calibration.result import CalibrationResult, Identifiability, PoseFit, SurfaceFit
from lrms.covariance import NoiseModel
from lrms.cylinder import BeamOptics
from lrms.kinematics import RigModel

_log = logging.getLogger(__name__)

__all__ = [
    "GOAL",
    "SPREAD",
    "AdjustOptions",
    "Artefact",
    "ArtefactError",
    "CalibrationError",
    "CalibrationOptions",
    "CalibrationResult",
    "CloudTooSmallError",
    "DetectOptions",
    "DetectionError",
    "DistanceSpec",
    "Identifiability",
    "Observations",
    "PoseFit",
    "RegistrationError",
    "SphereSpec",
    "SpotScale",
    "SurfaceFit",
    "apply_to_points",
    "calibrate",
]

#: Fewer valid beams than this is no calibration sweep.
MIN_OBSERVATIONS = 2000


@dataclass(frozen=True)
class CalibrationOptions:
    """``optics``: the scanner's nominal light spot (:class:`lrms.cylinder.BeamOptics`); given, the
    spot scale is estimated from the reference spheres' limb beams (:mod:`lrms.calibration.optics`);
    ``None`` (the thin beam): not estimated."""

    detect: DetectOptions = field(default_factory=DetectOptions)
    adjust: AdjustOptions = field(default_factory=AdjustOptions)
    optics: BeamOptics | None = None


def calibrate(
    sweeps: Sequence[Observations],
    artefact: Artefact,
    *,
    nominal: RigModel | None = None,
    noise: NoiseModel | None = None,
    options: CalibrationOptions | None = None,
    poses: str = "shared",
) -> CalibrationResult:
    """Estimate the rig (:class:`RigModel`) from calibration sweeps of ``artefact``.

    The surfaces are found in the cloud mapped with ``nominal`` (default: seed 003's Eq. 1), the
    parameters the data cannot determine are held at their nominal values (the result's
    identifiability report says which, why, and what data would determine them), and the others
    are adjusted jointly with the surfaces.

    ``poses``: "shared" (the sweeps were taken with the rig and the artefact unmoved: one cloud) or
    "separate" (the rig, or the whole artefact, moved between sweeps: each sweep after the first
    has its own unknown rigid pose, six parameters, adjusted jointly with the rig; the sweeps are
    registered first by the reference spheres they share, :mod:`lrms.calibration.poses`, which
    needs three common spheres off a line). Raises :class:`CloudTooSmallError`,
    :class:`DetectionError` (no planes / spheres found) or :class:`CalibrationError`.
    """
    nom = nominal if nominal is not None else RigModel()
    nm = noise if noise is not None else NoiseModel()
    opts = options if options is not None else CalibrationOptions()
    if poses not in ("shared", "separate"):
        raise CalibrationError(f"poses must be 'shared' or 'separate', got {poses!r}")
    separate = poses == "separate" and len(sweeps) > 1
    obs, which = concatenate(list(sweeps))
    if len(obs) < MIN_OBSERVATIONS:
        raise CloudTooSmallError(f"a calibration needs at least {MIN_OBSERVATIONS} valid beams, got {len(obs)}")
    if separate:
        if not artefact.spheres:
            raise CalibrationError("separate poses need reference spheres (three or more) to register the sweeps")
        found = []
        for k, s in enumerate(sweeps):
            try:
                found.append(_detect(s, artefact, nom, opts.detect))
            except CalibrationError as exc:
                raise type(exc)(f"sweep {k + 1}: {exc}") from None
        offsets = np.cumsum([0, *(len(s) for s in sweeps)])[:-1]
        planes, spheres, initial = merge(
            [f[0] for f in found], [f[1] for f in found], [int(o) for o in offsets], artefact=artefact
        )
    else:
        planes, spheres = _detect(obs, artefact, nom, opts.detect)
        initial = None

    rounds = 0

    def adjust(spot: tuple[float, float] | None) -> tuple[Adjustment, list[str], dict[str, str], Any, Any, Any]:
        nonlocal rounds
        adj = Adjustment(obs, planes, spheres, artefact, nom, nm, opts.adjust, which=which if separate else None,
                         poses=initial, spot=spot)  # fmt: skip
        adj._init_sigma()
        names, _, _ = adj.choose_free()
        adj.solve(names)  # a first estimate from the loose segmentation of the nominal cloud
        # re-segment under each new estimate until the surfaces' beam counts settle: beams outside
        # every surface's reach under a rough estimate come back once the estimate is better
        previous: dict[str, int] | None = None
        for rounds in range(1, opts.adjust.max_resegmentations + 1):
            counts = adj.resegment(opts.detect.min_plane_points, opts.adjust.outlier_sigma)
            names, held, eig = adj.choose_free()
            _log.debug("re-segmentation %d: %s", rounds, counts)
            if previous is not None and resegment_settled(previous, counts):
                break
            adj.solve(names)
            previous = counts
        adj.reject_outliers(names)
        r, jac, iterations = adj.solve(names)
        return adj, names, held, eig, (r, jac, iterations), adj.covariance(names, jac, r)

    # with optics, two stages: the rig with the nominal spot (footprint-censored, sphere ranges
    # corrected), the spot scale from the limb beams with that rig; when the scale differs from the
    # one assumed by more than 2 u, the rig again with the estimated spot and the scale again
    spot_scale = 1.0
    spot: SpotScale | None = None
    for _stage in range(2 if opts.optics is not None else 1):
        adj, names, held, eig, (r, _jac, iterations), (cov_free, s0sq, dof) = adjust(
            None if opts.optics is None else _spot_sigma(opts.optics, spot_scale)
        )
        if opts.optics is None:
            break
        spot = _spot_scale(adj, RigModel.from_vector(adj.state.rig), opts.optics, names, cov_free)
        if spot is None or abs(spot.scale - spot_scale) <= 2 * spot.u:
            break
        if _stage == 1:  # the rig was adjusted with another scale than the one it gives: say so
            _log.warning(
                "spot scale %.4g (u %.2g) differs from the %.4g the final adjustment assumed by more than 2 u",
                spot.scale, spot.u, spot_scale,
            )  # fmt: skip
            break
        spot_scale = spot.scale

    if not names:  # nothing to store: a "calibration" of the nominal rig would look like a real one
        raise CalibrationError(
            f"the sweeps determine none of the rig's parameters ({len(adj.state.planes)} planes, "
            f"{len(adj.state.spheres)} spheres, {len(obs)} beams; docs/calibration.md, identifiability rules): "
            + "; ".join(f"{n}: {why}" for n, why in held.items())
        )
    idx = [RigModel.NAMES.index(n) for n in names]
    cov = np.zeros((len(RigModel.NAMES), len(RigModel.NAMES)))
    cov[np.ix_(idx, idx)] = cov_free
    std = np.sqrt(np.clip(np.diag(cov_free), 0, None))
    weak = {
        n: f"std {s * RigModel.UNITS[n][1]:.3g} {RigModel.UNITS[n][0]} exceeds the goal "
        f"{GOAL[n] * RigModel.UNITS[n][1]:.3g} {RigModel.UNITS[n][0]}"
        for n, s in zip(names, std, strict=True)
        if s > GOAL[n]
    }
    scaled = cov_free / np.outer([SPREAD[n] for n in names], [SPREAD[n] for n in names]) if names else np.zeros((0, 0))
    info = np.linalg.eigvalsh(np.linalg.inv(scaled)) if names else np.zeros(1)
    ident = Identifiability(
        held={**{n: STRUCTURAL[n] for n in STRUCTURAL}, **held},
        rank=len(names),
        condition=float(info[-1] / info[0]) if info[0] > 0 else float("inf"),
        weak=weak,
        eigenvalues=tuple(float(x) for x in eig),
    )
    rows, metric = adj.surface_summary(names)
    surfaces = tuple(SurfaceFit(k, params, n, rms, ai) for k, params, n, rms, ai in rows)
    model = RigModel.from_vector(adj.state.rig)
    return CalibrationResult(
        model=model,
        nominal=nom,
        covariance=cov,
        estimated=tuple(names),
        identifiability=ident,
        surfaces=surfaces,
        residuals={
            "variance_factor": s0sq,
            "dof": float(dof),
            "observations": float(metric.size),
            "rms_m": float(np.sqrt(np.mean(metric**2))),
            "rms_weighted": float(np.sqrt(np.mean(r**2))),
            "iterations": float(iterations),
            "resegmentations": float(rounds),
            "planes": float(len(adj.state.planes)),
            "spheres": float(len(adj.state.spheres)),
        },
        artefact=artefact.to_dict(),
        sources=tuple(s.source for s in sweeps if s.source),
        created=datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
        software_version=lrms.__version__,
        poses=_pose_fits(adj, sweeps) if separate else (),
        optics=None
        if spot is None or opts.optics is None
        else {
            "spot_scale": spot.scale,
            "spot_scale_u": spot.u,
            "exit_diameter_m": opts.optics.exit_diameter_m,
            "divergence_rad": opts.optics.divergence_rad,
            "profile_sigma": opts.optics.profile_sigma,
            "extent": opts.optics.extent,
            "assumed_scale": spot_scale,
        },
        censored=dict(adj.censored) if opts.optics is not None else None,
    )


def _spot_sigma(optics: BeamOptics, scale: float) -> tuple[float, float]:
    """The spot's Gaussian sigma ``(s0, sd)`` (``sigma = s0 + sd x range``) for ``scale`` x the nominal."""
    return (optics.profile_sigma * optics.exit_diameter_m * scale, optics.profile_sigma * optics.divergence_rad * scale)


def _spot_scale(
    adj: Adjustment, model: RigModel, optics: BeamOptics, names: list[str], cov_free: np.ndarray
) -> SpotScale | None:
    """The spot scale from the adjusted spheres' limb beams (every sweep, placed by its pose);
    ``None`` without spheres or with too few limb beams. Its ``u`` includes the rig's: the scale's
    sensitivity to each free rig parameter (central differences, one standard deviation each way)
    propagated with the rig's covariance ``cov_free`` (the spheres' centres' is not included)."""
    if not adj.state.spheres:
        return None
    o = adj.obs
    spheres = [(sp.center, sp.radius_known) for sp in adj.state.spheres]

    def estimate(vec: np.ndarray) -> SpotScale | None:
        m = RigModel.from_vector(vec)
        org, d = adj._world(adj.state, np.arange(len(o)), *m.rays(o.alpha, o.beta, o.omega))
        return estimate_spot_scale(
            org, d, m.geometric_range(o.l), spheres, optics.exit_diameter_m, optics.divergence_rad,
            optics.profile_sigma, adj.noise.sigma_l, optics.extent,
        )  # fmt: skip

    base = model.vector()
    spot = estimate(base)
    if spot is None or not names:
        return spot
    std = np.sqrt(np.clip(np.diag(cov_free), 0, None))
    grad = np.zeros(len(names))
    for k, name in enumerate(names):
        if std[k] <= 0:
            continue
        j = RigModel.NAMES.index(name)
        up, dn = base.copy(), base.copy()
        up[j] += std[k]
        dn[j] -= std[k]
        hi, lo = estimate(up), estimate(dn)
        if hi is not None and lo is not None:
            grad[k] = (hi.scale - lo.scale) / (2 * std[k])
    u_rig2 = float(grad @ cov_free @ grad)
    return SpotScale(spot.scale, float(np.sqrt(spot.u**2 + max(u_rig2, 0.0))), spot.beams, spot.rms_m)


def _detect(
    obs: Observations, artefact: Artefact, nominal: RigModel, opts: DetectOptions
) -> tuple[list[PlaneSeg], list[SphereSeg]]:
    """Planes and spheres in the cloud of ``obs`` mapped with the nominal rig."""
    points = nominal.forward(obs.l, obs.alpha, obs.beta, obs.omega)
    return detect_surfaces(points, artefact, opts, np.random.default_rng(opts.seed))


def _pose_fits(adj: Adjustment, sweeps: Sequence[Observations]) -> tuple[PoseFit, ...]:
    out = []
    std = np.sqrt(np.clip(np.diag(adj.pose_covariance), 0, None))
    for k in range(adj.n_poses):
        t = np.eye(4)
        t[:3, :3], t[:3, 3] = adj.state.rot[k], adj.state.trans[k]
        s = tuple(float(x) for x in std[6 * (k - 1) : 6 * k]) if k else (0.0,) * 6
        out.append(PoseFit(k, t, s, sweeps[k].source))
    return tuple(out)


def apply_to_points(points: np.ndarray, calibration: CalibrationResult) -> np.ndarray:
    """Re-map a cloud mapped with the calibration's nominal rig (rig at the origin) with the
    calibrated rig: invert the nominal Eq. 1 to the readings, map them with the estimate."""
    obs = Observations.from_points(points, calibration.nominal.p)
    if len(obs) != len(points):
        raise CalibrationError("some points lie on the motor axis: their readings cannot be recovered")
    return calibration.model.forward(obs.l, obs.alpha, obs.beta)
