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

The generalised rig (:class:`RigModel`, issue 12) adds what a real rig gets wrong; its nominal
values reproduce Eq. 1 exactly. From reported ``(l, alpha, beta)`` and the motor speed ``omega``
(rad/s, signed; 0 when unknown)::

    L  = k0 + (1 + k1) l                                   range offset and scale
    a  = alpha + alpha_zero                                scanner angular zero
    b  = (1 + beta_scale) beta + beta_zero                 motor encoder scale and zero
         - (backlash / 2) sign(omega) + time_offset omega  backlash, scan/motor time offset
    c0 = (p, 0, q)                                         optical centre (q: across the scan plane)
    d0 = Ry(tilt_y) Rx(tilt_x) (sin a, cos a, 0)           scan-plane tilts
    point = Ry(b) (c0 + L d0)

with ``Rx(t)`` the rotation about x taking +y towards +z and ``Ry(t)`` the rotation about the
shaft taking +x towards +z (the motor's own sense: ``Ry(beta) (1, 0, 0) = (cos beta, 0, sin
beta)``). ``tilt_x`` tips the scan plane out of the shaft direction (the beam at alpha = 0 leaves
the shaft); ``tilt_y`` turns the scan plane about the shaft around the optical centre.

Not identifiable from a cloud (they move it rigidly, or are exactly another parameter):
``beta_zero`` (a rotation about the shaft), an offset of the optical centre along the shaft (a
translation along it; not a parameter here), and ``tilt_y``, which equals a change of
``beta_zero`` by ``tilt_y`` plus the optical centre turned by ``-tilt_y`` about the shaft
(:meth:`RigModel.canonical`). ``backlash`` and ``time_offset`` only show between sweeps in
opposite directions (backlash) or at different speeds (time offset); in one sweep at constant
speed they are a constant angle, i.e. ``beta_zero``.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import asdict, dataclass, field, fields, replace
from typing import Any, ClassVar

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


def inverse(
    xyz: ArrayLike, p: float = DEFAULT_P, *, half_turn: bool = False
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Inverse of Eq. 1: rig-frame points ``(..., 3)`` to ``(l, alpha, beta)``.

    A point has two readings, ``beta`` and ``beta + pi`` (the scan plane's two halves). By
    default the branch is chosen with ``l sin(alpha) + p >= 0`` (the point lies on the
    scanner's side of the shaft). With ``half_turn`` it is chosen with ``beta`` in
    ``[-pi/2, pi/2)``, which is the right one for every point of a sweep that stays within
    +-90 deg (both halves of the 270 deg scan: points on either side of the shaft).
    """
    pts = np.asarray(xyz, dtype=np.float64)
    if pts.shape[-1] != 3:
        raise LrmsError(f"points must have shape (..., 3), got {pts.shape}")
    x, y, z = pts[..., 0], pts[..., 1], pts[..., 2]
    if half_turn:
        beta = np.arctan2(z, x)
        flip = (beta >= np.pi / 2) | (beta < -np.pi / 2)
        beta = np.where(flip, np.where(beta >= np.pi / 2, beta - np.pi, beta + np.pi), beta)
        r = np.where(flip, -1.0, 1.0) * np.hypot(x, z)
    else:
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


def _rot_x(v0: FloatArray, v1: FloatArray, v2: FloatArray, t: float) -> tuple[FloatArray, FloatArray, FloatArray]:
    """``Rx(t) v``: +y towards +z."""
    c, s = np.cos(t), np.sin(t)
    return v0, c * v1 - s * v2, s * v1 + c * v2


def _rot_y(v0: ArrayLike, v1: ArrayLike, v2: ArrayLike, t: ArrayLike) -> tuple[FloatArray, FloatArray, FloatArray]:
    """``Ry(t) v``: +x towards +z (the motor's sense of Eq. 1)."""
    x, y, z, tt = (np.asarray(v, dtype=np.float64) for v in (v0, v1, v2, t))
    c, s = np.cos(tt), np.sin(tt)
    return c * x - s * z, np.broadcast_to(y, np.broadcast_shapes(y.shape, tt.shape)), s * x + c * z


@dataclass(frozen=True)
class RigModel:
    """The generalised rig of issue 12 (SI units; see the module docstring for the model).

    Every field but ``p`` is zero on a perfect rig; ``RigModel()`` is seed 003's Eq. 1.
    ``alpha_zero`` and ``beta_zero`` are corrections applied after :class:`RigCalibration`'s
    device conventions (``alpha_offset``, ``motor_zero``).
    """

    k0: float = 0.0
    """Range offset (m): the geometric range is ``k0 + (1 + k1) l``."""
    k1: float = 0.0
    """Range scale error (dimensionless; 1e-6 = 1 ppm)."""
    p: float = DEFAULT_P
    """Optical centre to motor axis, in the scan plane (m; seed 003: 0.1)."""
    q: float = 0.0
    """Optical centre offset across the scan plane (m)."""
    tilt_x: float = 0.0
    """Scan plane tipped out of the shaft direction (rad, about the in-plane axis across the shaft)."""
    tilt_y: float = 0.0
    """Scan plane turned about the shaft, around the optical centre (rad)."""
    alpha_zero: float = 0.0
    """Scanner angular zero error (rad), added to alpha."""
    beta_zero: float = 0.0
    """Motor encoder zero error (rad), added to beta (a rigid rotation: not identifiable)."""
    beta_scale: float = 0.0
    """Motor encoder scale error (dimensionless)."""
    backlash: float = 0.0
    """Backlash (rad): the scan plane lags the encoder by half of it in the direction of motion
    (an estimate may come out slightly negative)."""
    time_offset: float = 0.0
    """Scan/motor time offset (s): the plane angle at a beam is ``beta + time_offset * omega``."""

    #: Parameter order of vectors and matrices (:meth:`vector`, the calibration's covariance).
    NAMES: ClassVar[tuple[str, ...]] = (
        "k0", "k1", "p", "q", "tilt_x", "tilt_y", "alpha_zero", "beta_zero", "beta_scale", "backlash", "time_offset",
    )  # fmt: skip
    #: Display unit and factor from SI for each parameter.
    UNITS: ClassVar[dict[str, tuple[str, float]]] = {
        "k0": ("mm", 1e3),
        "k1": ("ppm", 1e6),
        "p": ("mm", 1e3),
        "q": ("mm", 1e3),
        "tilt_x": ("deg", float(np.rad2deg(1.0))),
        "tilt_y": ("deg", float(np.rad2deg(1.0))),
        "alpha_zero": ("deg", float(np.rad2deg(1.0))),
        "beta_zero": ("deg", float(np.rad2deg(1.0))),
        "beta_scale": ("ppm", 1e6),
        "backlash": ("deg", float(np.rad2deg(1.0))),
        "time_offset": ("ms", 1e3),
    }

    def __post_init__(self) -> None:
        for f in fields(self):
            v = getattr(self, f.name)
            if not isinstance(v, (int, float, np.floating, np.integer)) or not np.isfinite(v):
                raise LrmsError(f"rig parameter {f.name} must be a finite number, got {v!r}")
            object.__setattr__(self, f.name, float(v))
        if self.k1 <= -0.5 or self.beta_scale <= -0.5:
            raise LrmsError("range and motor scale errors must be > -0.5 (a factor 1 + k > 0.5)")
        if self.p < 0:
            raise LrmsError(f"inner parameter p must be a finite length >= 0, got {self.p}")

    # -- vectors and dictionaries ------------------------------------------------------------
    def vector(self) -> FloatArray:
        """The parameters in :attr:`NAMES` order (SI)."""
        return np.array([getattr(self, n) for n in self.NAMES], dtype=np.float64)

    @classmethod
    def from_vector(cls, values: ArrayLike) -> RigModel:
        v = np.asarray(values, dtype=np.float64)
        if v.shape != (len(cls.NAMES),):
            raise LrmsError(f"a rig parameter vector has {len(cls.NAMES)} values, got shape {v.shape}")
        return cls(**{n: float(x) for n, x in zip(cls.NAMES, v, strict=True)})

    def to_dict(self) -> dict[str, float]:
        """SI values by name."""
        return {k: float(v) for k, v in asdict(self).items()}

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> RigModel:
        """From SI values by name (unknown names are an error)."""
        unknown = set(data) - set(cls.NAMES)
        if unknown:
            raise LrmsError(f"unknown rig parameter(s): {', '.join(sorted(unknown))}")
        return cls(**{k: float(v) for k, v in data.items()})

    def display(self) -> dict[str, float]:
        """Values in display units (mm, ppm, deg, ms), keyed ``name_unit``."""
        return {f"{n}_{u}": getattr(self, n) * s for n, (u, s) in self.UNITS.items()}

    def is_nominal(self, p: float | None = None) -> bool:
        """True when every field is at its perfect-rig value (``p`` at ``p`` if given)."""
        ref = RigModel(p=self.p if p is None else p)
        return self == ref

    def canonical(self) -> RigModel:
        """The equivalent rig with ``tilt_y = 0``: the same cloud up to a rotation about the shaft.

        ``Ry(b) (c0 + L Ry(t) d) = Ry(b + t) (Ry(-t) c0 + L d)``: the tilt moves into ``beta_zero``
        and turns the optical centre ``(p, q)`` by ``-t`` about the shaft. Identifiable
        parameters of a calibration are compared with this form of the truth.
        """
        t = self.tilt_y
        c, s = np.cos(t), np.sin(t)
        return replace(
            self, tilt_y=0.0, beta_zero=self.beta_zero + t, p=float(self.p * c + self.q * s),
            q=float(-self.p * s + self.q * c),
        )  # fmt: skip

    # -- the model ---------------------------------------------------------------------------
    def plane_angle(self, beta: ArrayLike, omega: ArrayLike | None = None) -> FloatArray:
        """The scan plane's true angle ``b`` from reported beta (and motor speed omega, rad/s)."""
        b = (1.0 + self.beta_scale) * np.asarray(beta, dtype=np.float64) + self.beta_zero
        if omega is not None and (self.backlash != 0.0 or self.time_offset != 0.0):
            w = np.asarray(omega, dtype=np.float64)
            b = b - 0.5 * self.backlash * np.sign(w) + self.time_offset * w
        return np.asarray(b, dtype=np.float64)

    def geometric_range(self, l: ArrayLike) -> FloatArray:
        """``k0 + (1 + k1) l``: the distance from the optical centre for a reported range."""
        return np.asarray(self.k0 + (1.0 + self.k1) * np.asarray(l, dtype=np.float64), dtype=np.float64)

    def reported_range(self, geometric: ArrayLike) -> FloatArray:
        """Inverse of :meth:`geometric_range`: what this rig's scanner reports for a true distance."""
        return np.asarray((np.asarray(geometric, dtype=np.float64) - self.k0) / (1.0 + self.k1), dtype=np.float64)

    def rays(self, alpha: ArrayLike, beta: ArrayLike, omega: ArrayLike | None = None) -> tuple[FloatArray, FloatArray]:
        """Rig-frame beam origins and unit directions ``(..., 3)`` for reported angles."""
        a0, b0 = np.broadcast_arrays(np.asarray(alpha, float), np.asarray(beta, float))
        if omega is not None:
            a0, b0, w = np.broadcast_arrays(a0, b0, np.asarray(omega, float))
        if self.is_nominal():
            return beam_rays(a0, b0, self.p)  # Eq. 1, bit for bit
        a = a0 + self.alpha_zero
        b = self.plane_angle(b0, None if omega is None else w)
        # the beam in the scanner frame (beta = 0), tilted
        d = _rot_y(*_rot_x(np.sin(a), np.cos(a), np.zeros_like(a), self.tilt_x), self.tilt_y)
        dirs = np.stack(_rot_y(*d, b), axis=-1)
        origins = np.stack(_rot_y(self.p, 0.0, self.q, b), axis=-1)
        return origins, dirs

    def forward(self, l: ArrayLike, alpha: ArrayLike, beta: ArrayLike, omega: ArrayLike | None = None) -> FloatArray:
        """Reported ``(l, alpha, beta)`` (and motor speed) to rig-frame points ``(..., 3)``.

        The nominal model gives exactly :func:`forward` (Eq. 1).
        """
        l_, a, b = _broadcast3(l, alpha, beta)
        if self.is_nominal():
            return forward(l_, a, b, self.p)
        o, d = self.rays(a, b, omega)
        return np.asarray(o + self.geometric_range(l_)[..., None] * d, dtype=np.float64)


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
    * ``model``: the generalised rig (:class:`RigModel`: range offset and scale, optical centre,
      tilts, zeros, motor scale, backlash, time offset). Its ``p`` is this calibration's ``p``:
      give one or the other (both only when equal). Default: Eq. 1 with ``p``.
    """

    p: float = DEFAULT_P
    alpha_offset: float = -np.pi / 2
    alpha_sign: float = 1.0
    motor_zero: float = 0.0
    world_from_rig: FloatArray = field(default_factory=_identity)
    model: RigModel | None = None

    #: ``[kinematics]`` keys of the generalised model: key -> (RigModel field, factor to SI).
    MODEL_KEYS: ClassVar[dict[str, tuple[str, float]]] = {
        "range_offset_m": ("k0", 1.0),
        "range_scale_ppm": ("k1", 1e-6),
        "q_m": ("q", 1.0),
        "tilt_x_deg": ("tilt_x", float(np.deg2rad(1.0))),
        "tilt_y_deg": ("tilt_y", float(np.deg2rad(1.0))),
        "alpha_zero_deg": ("alpha_zero", float(np.deg2rad(1.0))),
        "beta_zero_deg": ("beta_zero", float(np.deg2rad(1.0))),
        "motor_scale_ppm": ("beta_scale", 1e-6),
        "backlash_deg": ("backlash", float(np.deg2rad(1.0))),
        "time_offset_s": ("time_offset", 1.0),
    }

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
        if self.model is None:
            object.__setattr__(self, "model", RigModel(p=float(self.p)))
        elif not isinstance(self.model, RigModel):
            raise LrmsError(f"model must be a RigModel, got {type(self.model).__name__}")
        elif self.model.p != self.p:
            if self.p != DEFAULT_P:
                raise LrmsError(f"p ({self.p}) and model.p ({self.model.p}) disagree: give one of them")
            object.__setattr__(self, "p", self.model.p)

    @property
    def rig(self) -> RigModel:
        """The generalised rig model (never None after construction)."""
        assert self.model is not None
        return self.model

    def with_model(self, model: RigModel) -> RigCalibration:
        """This calibration with another rig model (its ``p`` included)."""
        return replace(self, p=model.p, model=model)

    @classmethod
    def from_dict(cls, cfg: Mapping[str, Any]) -> RigCalibration:
        """Build from a config table (TOML ``[kinematics]``): angles in degrees.

        Keys: ``p_m``, ``alpha_offset_deg``, ``alpha_sign``, ``motor_zero_deg``,
        ``world_from_rig`` (4x4 nested list), and the generalised rig's :attr:`MODEL_KEYS`
        (``range_offset_m``, ``range_scale_ppm``, ``q_m``, ``tilt_x_deg``, ``tilt_y_deg``,
        ``alpha_zero_deg``, ``beta_zero_deg``, ``motor_scale_ppm``, ``backlash_deg``,
        ``time_offset_s``; all 0 by default). Unknown keys are an error.
        """
        known = {"p_m", "alpha_offset_deg", "alpha_sign", "motor_zero_deg", "world_from_rig", *cls.MODEL_KEYS}
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
        extra = {fld: float(cfg[key]) * f for key, (fld, f) in cls.MODEL_KEYS.items() if key in cfg}
        if extra:
            kwargs["model"] = RigModel(p=kwargs.get("p", DEFAULT_P), **extra)
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

    def map_samples(
        self, ranges_m: ArrayLike, device_angle: ArrayLike, motor_angle: ArrayLike, motor_speed: ArrayLike | None = None
    ) -> FloatArray:
        """Device readings to world-frame points ``(..., 3)`` (Eq. 1 plus calibration).

        ``motor_speed`` (rad/s) is used only by the backlash and time-offset terms of the model.
        """
        pts = self.rig.forward(ranges_m, self.alpha(device_angle), self.beta(motor_angle), motor_speed)
        return self.to_world(pts)

    def rays(
        self, alpha: ArrayLike, beta: ArrayLike, motor_speed: ArrayLike | None = None
    ) -> tuple[FloatArray, FloatArray]:
        """World-frame beam origins and unit directions for scan angles alpha and plane angles beta."""
        o, d = self.rig.rays(alpha, beta, motor_speed)
        rot = self.world_from_rig[:3, :3]
        return self.to_world(o), np.asarray(d @ rot.T, dtype=np.float64)

    def world_rays(
        self, device_angle: ArrayLike, motor_angle: ArrayLike, motor_speed: ArrayLike | None = None
    ) -> tuple[FloatArray, FloatArray]:
        """World-frame beam origins and unit directions for device beam angles at a motor angle."""
        return self.rays(self.alpha(device_angle), self.beta(motor_angle), motor_speed)
