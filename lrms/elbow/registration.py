"""Registration of two clouds by one elbow joint (seed 000, Eq. 11), with its uncertainty.

Eq. 11 with this project's rotation ``R = R2(kappa) R3(psi) R1(omega)`` (world to model)::

    x' = R_1^T R_2 (x - c_2) + c_1

takes cloud 2 into cloud 1's frame: the rotation is ``R_r = R_1^T R_2`` and the translation
``t = c_1 - R_r c_2``. Both fits must label the joint's legs alike (:func:`lrms.elbow.canonical`
labels the longer visible leg as the start leg); a pure bend seen without legs has a two-fold
ambiguity that no single joint can resolve.

Uncertainty: the fits are independent; each contributes the covariance of its centre and small
rotation ``w`` (``R <- (I - [w]x) R``). To first order the transform's small rotation
``e`` (``R_r <- (I + [e]x) R_r``) is ``e = R_1^T (w_1 - w_2)`` and the translation changes by
``dt = dc_1 - R_r dc_2 + [R_r c_2]x e``; the 6x6 covariance of ``(t, e)`` follows. ``t`` is
where cloud 2's origin lands, so its uncertainty carries the lever arm ``|c_2|``;
``sigma_at_joint`` is the uncertainty of a point at the joint after the transform.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from lrms.elbow.gauss_helmert import ElbowFit
from lrms.elbow.model import skew
from lrms.errors import FitError

FloatArray = NDArray[np.float64]

#: Two fits whose diameters differ by more than this fraction are not the same joint.
MAX_DIAMETER_MISMATCH = 0.1


@dataclass(frozen=True)
class Registration:
    """The rigid transform taking cloud 2 into cloud 1's frame."""

    matrix: FloatArray  # 4x4 homogeneous
    cov: FloatArray  # 6x6 covariance of (translation (m), small rotation (rad)) in frame 1
    sigma_at_joint: FloatArray  # (3,) standard deviation (m) of the joint centre mapped into frame 1
    diameter_difference: float  # D_1 - D_2 (m)
    bend_radius_difference: float  # A_1 - A_2 (m)

    @property
    def rotation(self) -> FloatArray:
        return np.asarray(self.matrix[:3, :3])

    @property
    def translation(self) -> FloatArray:
        return np.asarray(self.matrix[:3, 3])

    @property
    def sigma_translation(self) -> FloatArray:
        return np.asarray(np.sqrt(np.clip(np.diag(self.cov)[:3], 0.0, None)))

    @property
    def sigma_rotation_deg(self) -> FloatArray:
        return np.asarray(np.degrees(np.sqrt(np.clip(np.diag(self.cov)[3:], 0.0, None))))

    def apply(self, points: ArrayLike) -> FloatArray:
        """Cloud 2 points expressed in cloud 1's frame."""
        p = np.asarray(points, dtype=np.float64)
        return np.asarray(p @ self.rotation.T + self.translation)

    def to_dict(self) -> dict[str, object]:
        return {
            "matrix": [[float(x) for x in row] for row in self.matrix],
            "sigma_translation_m": [float(x) for x in self.sigma_translation],
            "sigma_rotation_deg": [float(x) for x in self.sigma_rotation_deg],
            "sigma_at_joint_m": [float(x) for x in self.sigma_at_joint],
            "rotation_angle_deg": rotation_angle_deg(self.rotation),
            "diameter_difference_m": self.diameter_difference,
            "bend_radius_difference_m": self.bend_radius_difference,
        }


def rotation_angle_deg(rot: ArrayLike) -> float:
    """Angle of a rotation matrix (deg)."""
    r = np.asarray(rot, dtype=np.float64)
    return math.degrees(math.acos(float(np.clip((np.trace(r) - 1.0) / 2.0, -1.0, 1.0))))


def register(fit1: ElbowFit, fit2: ElbowFit) -> Registration:
    """Eq. 11: the transform taking cloud 2 (fitted by ``fit2``) into cloud 1's frame."""
    p1, p2 = fit1.params, fit2.params
    if abs(p1.degree - p2.degree) > 1e-9:
        raise FitError(
            f"the two fits are different joints: {math.degrees(p1.degree):.1f} deg and "
            f"{math.degrees(p2.degree):.1f} deg"
        )
    if abs(p1.D - p2.D) > MAX_DIAMETER_MISMATCH * max(p1.D, p2.D):
        raise FitError(f"the two fits are different joints: diameters {p1.D * 1e3:.1f} mm and {p2.D * 1e3:.1f} mm")
    rr = p1.rot.T @ p2.rot
    t = p1.center - rr @ p2.center
    mat = np.eye(4)
    mat[:3, :3] = rr
    mat[:3, 3] = t
    r1t = p1.rot.T
    lever = skew(rr @ p2.center)
    # Jacobian of (t, e) w.r.t. (c1, w1, c2, w2)
    jac = np.zeros((6, 12))
    jac[:3, 0:3] = np.eye(3)
    jac[:3, 3:6] = lever @ r1t
    jac[:3, 6:9] = -rr
    jac[:3, 9:12] = -lever @ r1t
    jac[3:, 3:6] = r1t
    jac[3:, 9:12] = -r1t
    cin = np.zeros((12, 12))
    cin[:6, :6] = fit1.cov[:6, :6]
    cin[6:, 6:] = fit2.cov[:6, :6]
    cov = jac @ cin @ jac.T
    # a point at the joint maps to x' = R_r (x - c2) + c1: only the two centres matter there
    cj = fit1.cov[:3, :3] + rr @ fit2.cov[:3, :3] @ rr.T
    sj = np.sqrt(np.clip(np.diag(cj), 0.0, None))
    return Registration(mat, np.asarray(cov), np.asarray(sj), p1.D - p2.D, p1.A - p2.A)
