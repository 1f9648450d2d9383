"""Rig kinematics: seed 003, Eq. 1, and the rig calibration.

The rig frame (RCS) has its y axis on the motor shaft, z straight up. The scanner's optical
centre sits at distance ``p`` (the *inner parameter*) from the shaft, in the x-z plane; the
scan plane contains the shaft direction and turns with the motor angle ``beta``. A sample of
range ``l`` at scan angle ``alpha`` (measured in the scan plane from the shaft direction +y)
maps to::

    x = (l sin(alpha) + p) cos(beta)
    y =  l cos(alpha)
    z = (l sin(alpha) + p) sin(beta)

So the beam starts at ``p (cos beta, 0, sin beta)`` and runs along
``(sin alpha cos beta, cos alpha, sin alpha sin beta)``.

The device reports its own angles (LMS1xx: -45 deg .. 225 deg, 90 deg straight ahead) and the
drive reports its own shaft angle; :class:`RigCalibration` turns those into ``alpha`` and
``beta`` and places the rig in a world frame.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from lrms.errors import LrmsError

FloatArray = NDArray[np.float64]

#: The seed's rig: distance from the optical centre to the motor axis (m).
DEFAULT_P = 0.1


def _broadcast3(l: ArrayLike, alpha: ArrayLike, beta: ArrayLike) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Float arrays of (l, alpha, beta) broadcast together; a clear error if their shapes clash.

    Non-finite values pass through (NaN in, NaN out): a beam without an echo stays marked.
    """
    try:
        l_, a, b = np.broadcast_arrays(np.asarray(l, float), np.asarray(alpha, float), np.asarray(beta, float))
    except ValueError:
        shapes = [np.shape(v) for v in (l, alpha, beta)]
        raise LrmsError(f"range, alpha and beta do not broadcast together: shapes {shapes}") from None
    return l_, a, b


def forward(l: ArrayLike, alpha: ArrayLike, beta: ArrayLike, p: float = DEFAULT_P) -> FloatArray:
    """Eq. 1: map (range, scan angle, motor angle) to rig-frame points, shape ``(..., 3)``.

    Inputs broadcast against each other.
    """
    l_, a, b = _broadcast3(l, alpha, beta)
    r = l_ * np.sin(a) + p
    out = np.empty((*l_.shape, 3), dtype=np.float64)
    out[..., 0] = r * np.cos(b)
    out[..., 1] = l_ * np.cos(a)
    out[..., 2] = r * np.sin(b)
    return out


def inverse(xyz: ArrayLike, p: float = DEFAULT_P) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Inverse of Eq. 1: rig-frame points ``(..., 3)`` to ``(l, alpha, beta)``.

    The branch is chosen with ``l sin(alpha) + p >= 0`` (the point lies on the scanner's side of
    the shaft), which holds for every point the rig can see beyond ``p`` from the shaft.
    """
    pts = np.asarray(xyz, dtype=np.float64)
    if pts.shape[-1] != 3:
        raise LrmsError(f"points must have shape (..., 3), got {pts.shape}")
    x, y, z = pts[..., 0], pts[..., 1], pts[..., 2]
    beta = np.arctan2(z, x)
    r = np.hypot(x, z)
    s = r - p  # l sin(alpha)
    l = np.hypot(s, y)
    alpha = np.arctan2(s, y)
    return l, alpha, beta


def beam_rays(alpha: ArrayLike, beta: ArrayLike, p: float = DEFAULT_P) -> tuple[FloatArray, FloatArray]:
    """Origins and unit directions (rig frame) of beams at ``alpha`` with the plane at ``beta``."""
    a, b = np.broadcast_arrays(np.asarray(alpha, float), np.asarray(beta, float))
    cb, sb, sa = np.cos(b), np.sin(b), np.sin(a)
    origins = np.stack([p * cb, np.zeros_like(b), p * sb], axis=-1)
    dirs = np.stack([sa * cb, np.cos(a), sa * sb], axis=-1)
    return origins, dirs


def jacobian(l: ArrayLike, alpha: ArrayLike, beta: ArrayLike, p: float = DEFAULT_P) -> FloatArray:
    """Eq. 6: d(x, y, z)/d(l, alpha, beta), shape ``(..., 3, 3)``."""
    l_, a, b = _broadcast3(l, alpha, beta)
    sa, ca, sb, cb = np.sin(a), np.cos(a), np.sin(b), np.cos(b)
    r = l_ * sa + p
    j = np.empty((*l_.shape, 3, 3), dtype=np.float64)
    j[..., 0, 0] = sa * cb
    j[..., 0, 1] = l_ * ca * cb
    j[..., 0, 2] = -r * sb
    j[..., 1, 0] = ca
    j[..., 1, 1] = -l_ * sa
    j[..., 1, 2] = 0.0
    j[..., 2, 0] = sa * sb
    j[..., 2, 1] = l_ * ca * sb
    j[..., 2, 2] = r * cb
    return j


def _identity() -> FloatArray:
    return np.eye(4)


@dataclass(frozen=True)
class RigCalibration:
    """Everything that turns device readings into rig-frame and world-frame geometry.

    * ``p``: optical centre to motor axis (m), seed 003: 0.1 m.
    * ``alpha = alpha_sign * device_angle + alpha_offset``. The LMS1xx reports 90 deg straight
      ahead; the default offset of -90 deg makes "straight ahead" the shaft direction (+y), as
      in the seed's set-up where the part stands about 2.5 m along +y.
    * ``beta = motor_angle - motor_zero`` (output-shaft radians).
    * ``world_from_rig``: 4x4 homogeneous pose of the rig frame in the world frame.
    """

    p: float = DEFAULT_P
    alpha_offset: float = -np.pi / 2
    alpha_sign: float = 1.0
    motor_zero: float = 0.0
    world_from_rig: FloatArray = field(default_factory=_identity)

    def __post_init__(self) -> None:
        t = np.asarray(self.world_from_rig, dtype=np.float64)
        if t.shape != (4, 4) or not np.allclose(t[3], [0, 0, 0, 1]):
            raise LrmsError("world_from_rig must be a 4x4 homogeneous transform")
        rot = t[:3, :3]
        if not np.allclose(rot @ rot.T, np.eye(3), atol=1e-9) or np.linalg.det(rot) < 0:
            raise LrmsError("world_from_rig rotation must be orthonormal and right-handed")
        if self.alpha_sign not in (1.0, -1.0):
            raise LrmsError("alpha_sign must be +1 or -1")
        if not np.isfinite(self.p) or self.p < 0:
            raise LrmsError(f"inner parameter p must be a finite length >= 0, got {self.p}")
        object.__setattr__(self, "world_from_rig", t)

    @classmethod
    def from_dict(cls, cfg: Mapping[str, Any]) -> RigCalibration:
        """Build from a config table (TOML ``[kinematics]``): angles in degrees.

        Keys: ``p_m``, ``alpha_offset_deg``, ``alpha_sign``, ``motor_zero_deg``,
        ``world_from_rig`` (4x4 nested list). Unknown keys are an error.
        """
        known = {"p_m", "alpha_offset_deg", "alpha_sign", "motor_zero_deg", "world_from_rig"}
        unknown = set(cfg) - known
        if unknown:
            raise LrmsError(f"unknown kinematics key(s): {', '.join(sorted(unknown))}")
        kwargs: dict[str, Any] = {}
        if "p_m" in cfg:
            kwargs["p"] = float(cfg["p_m"])
        if "alpha_offset_deg" in cfg:
            kwargs["alpha_offset"] = float(np.deg2rad(cfg["alpha_offset_deg"]))
        if "alpha_sign" in cfg:
            kwargs["alpha_sign"] = float(cfg["alpha_sign"])
        if "motor_zero_deg" in cfg:
            kwargs["motor_zero"] = float(np.deg2rad(cfg["motor_zero_deg"]))
        if "world_from_rig" in cfg:
            kwargs["world_from_rig"] = np.asarray(cfg["world_from_rig"], dtype=np.float64)
        return cls(**kwargs)

    def alpha(self, device_angle: ArrayLike) -> FloatArray:
        """Scan angle alpha (rad) from the device's beam angle (rad)."""
        return self.alpha_sign * np.asarray(device_angle, dtype=np.float64) + self.alpha_offset

    def device_angle(self, alpha: ArrayLike) -> FloatArray:
        """Inverse of :meth:`alpha`."""
        return (np.asarray(alpha, dtype=np.float64) - self.alpha_offset) * self.alpha_sign

    def beta(self, motor_angle: ArrayLike) -> FloatArray:
        """Scan-plane angle beta (rad) from the drive's output-shaft angle (rad)."""
        return np.asarray(motor_angle, dtype=np.float64) - self.motor_zero

    def motor_angle(self, beta: ArrayLike) -> FloatArray:
        return np.asarray(beta, dtype=np.float64) + self.motor_zero

    def to_world(self, rig_points: ArrayLike) -> FloatArray:
        pts = np.asarray(rig_points, dtype=np.float64)
        t = self.world_from_rig
        return pts @ t[:3, :3].T + t[:3, 3]

    def to_rig(self, world_points: ArrayLike) -> FloatArray:
        pts = np.asarray(world_points, dtype=np.float64)
        t = self.world_from_rig
        return (pts - t[:3, 3]) @ t[:3, :3]

    def map_samples(self, ranges_m: ArrayLike, device_angle: ArrayLike, motor_angle: ArrayLike) -> FloatArray:
        """Device readings to world-frame points ``(..., 3)`` (Eq. 1 plus calibration)."""
        pts = forward(ranges_m, self.alpha(device_angle), self.beta(motor_angle), self.p)
        return self.to_world(pts)

    def world_rays(self, device_angle: ArrayLike, motor_angle: ArrayLike) -> tuple[FloatArray, FloatArray]:
        """World-frame beam origins and unit directions for device beam angles at a motor angle."""
        o, d = beam_rays(self.alpha(device_angle), self.beta(motor_angle), self.p)
        rot = self.world_from_rig[:3, :3]
        return self.to_world(o), d @ rot.T
