"""Tuning of the detection and the fit."""

from __future__ import annotations

from dataclasses import dataclass


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
    models the footprint: the radius range's upper bound is raised by the spot radius at the
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
