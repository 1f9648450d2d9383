"""Tuning of the detection and the fit."""

from __future__ import annotations

from dataclasses import dataclass

#: The detection's allowance for the footprint (:meth:`DetectOptions.widening`), in spot radii
#: (the 1/e^2 radius at the part's range) per side. The thin-beam fit of seed 003's part at 2.5 m
#: in the room (LMS1xx footprint, 128 sub-rays, one sweep each) came out wider by 0.0 (50 % first
#: hit), 0.78 (50 % energy-weighted), 0.98 (10 % first hit), 1.02 (30 % energy-weighted) and 1.48
#: (10 % energy-weighted) spot radii; with one radius allowed, the 10 % energy-weighted member's
#: detection failed on 395 of 400 sweeps (issue 11, session 11).
FOOTPRINT_WIDENING = 2.0


@dataclass(frozen=True)
class DetectOptions:
    """Tuning of :func:`detect_cylinder` and :func:`fit_cylinder`; distances in metres.

    ``attempts``: independent RANSAC runs (stopping early at a plausible fit); while no fit is
    plausible (see :func:`_plausible`) up to ``max_attempts``. The best fit by :func:`_better` wins.
    ``grazing_sigma``: the lateral term of the line-of-sight fit's weights (m; negative: the
    default :data:`GRAZING_SIGMA`; 0: the plain maximum-likelihood fit), see
    :func:`grazing_weighted_fit`. ``bias_correction``: subtract the fit's second-order bias
    (:func:`second_order_bias`) from a line-of-sight fit.

    Background planes (:func:`lrms.cylinder.detect.dominant_planes`): up to ``max_planes`` planes
    (walls, floor, ceiling, table tops) are set aside before the cylinder RANSAC, each holding at
    least ``wall_min_share`` of the working sample and spanning at least ``wall_min_extent`` in both
    directions of the plane; points count when within ``threshold`` of the plane and their normal
    within about 30 deg of its normal (a cylinder of D >= 0.1 m is not a plane at that scale).
    ``max_planes = 0`` switches this off. The planes only steer the detection; the fit and the
    table's height use every point. ``spot``: the beam's (exit diameter, divergence) when the fit
    models the footprint: the radius range's upper bound is raised by :meth:`widening` at the
    candidate's range in the detection stages.
    """

    sample_size: int = 2000
    normal_k: int = 32
    threshold: float = 0.03
    normal_weight: float = 0.02
    radius_range: tuple[float, float] = (0.01, 2.0)
    plane_threshold: float = 0.02
    plane_normal_weight: float = 0.02
    plane_min_share: float = 0.05
    max_trials: int = 2000
    min_trials: int = 200
    min_inliers: int = 20
    attempts: int = 3
    max_attempts: int = 10
    grazing_sigma: float = -1.0
    bias_correction: bool = True
    max_planes: int = 6
    wall_min_share: float = 0.03
    wall_min_extent: float = 0.5
    wall_sample: int = 3_000
    spot: tuple[float, float] = (0.0, 0.0)

    def widening(self, range_m: float) -> float:
        """How much wider than the part (per side, m) a thin-beam fit of a footprint cloud may
        come out at ``range_m`` from the rig: :data:`FOOTPRINT_WIDENING` spot radii (0 without
        ``spot``)."""
        return FOOTPRINT_WIDENING * 0.5 * (self.spot[0] + self.spot[1] * range_m)
