"""Pipe elbow joints (seed 000): the torus model family, Gauss-Helmert fitting, automatic initial
values, registration from two fits, and mounting-bracket detection.

Typical use::

    from lrms.elbow import fit_auto
    fit = fit_auto(points, degree=math.radians(90), ratio=None, flange=False)
    print(fit.to_dict())
"""

from lrms.elbow.bounds import MetricFloors, metric_floors, parameter_floor
from lrms.elbow.gauss_helmert import ElbowFit, design_matrices, fit_elbow, param_names
from lrms.elbow.initial import initial_values
from lrms.elbow.model import (
    ElbowParams,
    condition,
    condition_seed,
    euler_from_matrix,
    parse_degree,
    parse_ratio,
    portions,
    rotation_matrix,
)
from lrms.elbow.pipeline import canonical, fit_auto

__all__ = [
    "ElbowFit",
    "ElbowParams",
    "MetricFloors",
    "canonical",
    "condition",
    "condition_seed",
    "design_matrices",
    "euler_from_matrix",
    "fit_auto",
    "fit_elbow",
    "initial_values",
    "metric_floors",
    "param_names",
    "parameter_floor",
    "parse_degree",
    "parse_ratio",
    "portions",
    "rotation_matrix",
]
