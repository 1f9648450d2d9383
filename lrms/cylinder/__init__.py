"""Cylinder detection and fitting that honours the rig's noise model.

Modules by job: :mod:`~lrms.cylinder.model` (the cylinder, beams, ray intersection, normals),
:mod:`~lrms.cylinder.refine` (residuals, Jacobians, :func:`refine_cylinder`),
:mod:`~lrms.cylinder.bias` (grazing weights, second-order bias correction),
:mod:`~lrms.cylinder.detect` (RANSAC model, support plane, table height),
:mod:`~lrms.cylinder.grid` (the detection's normals and nearest neighbours on grids),
:mod:`~lrms.cylinder.options` (:class:`DetectOptions`) and :mod:`~lrms.cylinder.pipeline`
(:func:`fit_cylinder`). Every public name is re-exported here.

Pipeline (:func:`fit_cylinder`; the details and measured numbers are in ``docs/cylinder.md``):

1. **Normals** on a random subsample by PCA of grid-cell neighbourhoods of about k points
   (:mod:`~lrms.cylinder.grid`, numpy only), as PCL's ``SACMODEL_CYLINDER`` expects them. The
   subsample keeps the neighbourhoods wider than the range noise (about 12 mm on the LMS100), so
   the normals mean something.
2. **Cylinder RANSAC** on minimal samples of 2 points + normals (:class:`CylinderModel`): the
   axis direction is ``n1 x n2``, the axis passes through the closest points of the two normal
   lines, the radius is the distance of the first point from that axis. Residual: distance to
   the surface plus a penalty for the angle between the point's normal and the radial direction.
3. **Support plane** (:func:`support_plane`): the populated slab perpendicular to the axis (the
   table); its points are set aside and the axis meets it at the base point.
4. **Refinement** with our own Levenberg-Marquardt (:mod:`~lrms.cylinder.lm`, analytic Jacobians):

   * *line of sight* (default): every point keeps its beam (origin and direction recovered by
     inverting Eq. 1) and the residual is the measured range minus the range at which that beam
     meets the model cylinder, divided by ``sigma_l``. This is the maximum-likelihood fit for the
     rig's noise, which lies almost entirely along the beam (Eq. 7). A beam that misses the model
     gets a second residual, its miss distance over a lateral sigma floored at
     :data:`SILHOUETTE_SIGMA`, so the objective stays continuous at the silhouette. Inliers are
     re-selected on the candidates (range residual below :data:`INLIER_GATE` sigma, miss below
     :data:`MISS_GATE` lateral sigmas, with hysteresis), then the fit is restarted from nearby
     radii (:data:`MULTISTART`, each start given :data:`MULTISTART_SCREEN` steps, then continued
     where it is best) because the silhouette makes the likelihood multi-modal.
   * *orthogonal distance* (``line_of_sight=False``): ``(|distance to axis| - r) / sigma``, the
     right fit for isotropic noise. On a one-sided view with range noise it is biased low.

5. Up to ``DetectOptions.attempts`` RANSAC runs (more while no fit is explained by the noise
   model); the best fit by :func:`_better` is kept.
6. **Selection by the scene model** (:func:`table_height`, :func:`_select_above_table`): the
   table is the plane perpendicular to the fitted axis under the part; the part's beams are
   those whose predicted first hit on the fitted part lies at least :data:`BASE_CLEARANCE` above
   it and not above the part's top (:func:`_top_height`); refit on them.
7. **Grazing weights** (:func:`grazing_weighted_fit`): the inliers are refitted with per-beam
   variances ``sigma_l^2 + (tan(incidence) sigma_lat)^2``, which moderates the leverage of the
   near-tangent limb beams (a trade of spread for a small bias, measured in docs/cylinder.md).
8. **Second-order bias correction** (:func:`second_order_bias`, Box 1971): the range of a beam
   near the silhouette is strongly curved in the parameters, which biases the nonlinear fit by
   about +0.07 mm in diameter on the seed's set-up; the bias is estimated at the solution and
   subtracted.

The parameters' covariance is expressed in a local frame at the solution: ``theta = (t1, t2,
s1, s2, r)``, the axis direction ``normalize(w + t1 e1 + t2 e2)``, the axis point ``a + s1 e1 +
s2 e2`` and the radius ``r``, where ``e1, e2`` (:attr:`CylinderFit.frame`) are perpendicular to the
fitted direction ``w`` and ``a`` is the fitted axis point.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from lrms.cylinder.bias import (
    _COS_FLOOR,
    GRAZING_SIGMA,
    _fit_frame,
    bias_corrected,
    grazing_sigmas,
    grazing_weighted_fit,
    incidence_cosines,
    second_order_bias,
)
from lrms.cylinder.detect import (
    TOP_BIN,
    Background,
    CylinderModel,
    _top_height,
    background_planes,
    candidate_pool,
    detect_cylinder,
    detect_plane,
    dominant_planes,
    support_plane,
    table_height,
)
from lrms.cylinder.grid import grid_normals, nearest_in_grid
from lrms.cylinder.model import (
    SILHOUETTE_SIGMA,
    Cylinder,
    Rays,
    _dot,
    _ray_cylinder,
    _unit,
    estimate_normals,
    perpendicular_frame,
    rays_from_points,
)
from lrms.cylinder.options import (
    DetectOptions,
)
from lrms.cylinder.pipeline import (
    BASE_CLEARANCE,
    CHI2_PLAUSIBLE,
    MULTISTART,
    MULTISTART_SCREEN,
    NOMINAL_K,
    NOMINAL_TOLERANCE,
    _better,
    _los_fit,
    _multistart,
    _noise_explains,
    _off_support,
    _plausible,
    _refine_from,
    _reindex,
    _select_above_table,
    diameter_u,
    fit_cylinder,
    nominal_check,
    nominal_diameter_range,
)
from lrms.cylinder.refine import (
    _STEPS,
    INLIER_GATE,
    MISS_GATE,
    CylinderFit,
    Residuals,
    _covariance,
    _Frame,
    _param_derivatives,
    _solve,
    central_jacobian,
    los_jacobian,
    los_residuals,
    orthogonal_jacobian,
    orthogonal_residuals,
    refine_cylinder,
)

__all__ = [
    "BASE_CLEARANCE",
    "CHI2_PLAUSIBLE",
    "GRAZING_SIGMA",
    "INLIER_GATE",
    "LMS1XX_DIVERGENCE",
    "LMS1XX_EXIT_DIAMETER",
    "MISS_GATE",
    "MULTISTART",
    "MULTISTART_SCREEN",
    "NOMINAL_K",
    "NOMINAL_TOLERANCE",
    "SILHOUETTE_SIGMA",
    "TOP_BIN",
    "_COS_FLOOR",
    "_STEPS",
    "Background",
    "BeamOptics",
    "Cylinder",
    "CylinderFit",
    "CylinderModel",
    "DetectOptions",
    "Rays",
    "Residuals",
    "_Frame",
    "_better",
    "_covariance",
    "_dot",
    "_fit_frame",
    "_los_fit",
    "_multistart",
    "_noise_explains",
    "_off_support",
    "_param_derivatives",
    "_plausible",
    "_ray_cylinder",
    "_refine_from",
    "_reindex",
    "_select_above_table",
    "_solve",
    "_top_height",
    "_unit",
    "background_planes",
    "bias_corrected",
    "candidate_pool",
    "central_jacobian",
    "detect_cylinder",
    "detect_plane",
    "diameter_u",
    "dominant_planes",
    "estimate_normals",
    "expected_echo",
    "fit_cylinder",
    "footprint_fit",
    "grazing_sigmas",
    "grazing_weighted_fit",
    "grid_normals",
    "incidence_cosines",
    "los_jacobian",
    "los_residuals",
    "nearest_in_grid",
    "nominal_check",
    "nominal_diameter_range",
    "orthogonal_jacobian",
    "orthogonal_residuals",
    "perpendicular_frame",
    "rays_from_points",
    "refine_cylinder",
    "second_order_bias",
    "support_plane",
    "table_height",
]

if TYPE_CHECKING:
    from lrms.cylinder.footprint import (
        LMS1XX_DIVERGENCE,
        LMS1XX_EXIT_DIAMETER,
        BeamOptics,
        expected_echo,
        footprint_fit,
    )

#: Loaded on first use (PEP 562): the footprint model imports scipy.special, about 0.3 s of
#: ``lrms fit``'s start, which the thin-beam fit does not need.
_FOOTPRINT = ("LMS1XX_DIVERGENCE", "LMS1XX_EXIT_DIAMETER", "BeamOptics", "expected_echo", "footprint_fit")


def __getattr__(name: str) -> Any:
    if name in _FOOTPRINT:
        from lrms.cylinder import footprint

        return getattr(footprint, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
