"""Inputs of a rig calibration: raw observations of sweeps and the artefact description."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from lrms import kinematics
from lrms.errors import LrmsError

FloatArray = NDArray[np.float64]

#: Default standard uncertainty of a calibrated sphere's diameter and of a sphere-bar length (m).
DEFAULT_U_DIAMETER = 5e-6
DEFAULT_U_DISTANCE = 10e-6


class CalibrationError(LrmsError):
    """A calibration cannot be made from the given data (typed subclasses say why)."""


class ArtefactError(CalibrationError):
    """The artefact description is malformed (negative diameter, unknown key, bad index, ...)."""


class CloudTooSmallError(CalibrationError):
    """Too few valid observations for a calibration."""


class DetectionError(CalibrationError):
    """A surface the artefact promises was not found in the cloud (no planes, no spheres, ...)."""


@dataclass(frozen=True)
class Observations:
    """Raw readings of one sweep: range ``l`` (m), scan angle ``alpha`` and plane angle ``beta``
    (rad, as :class:`~lrms.kinematics.RigCalibration` makes them from the device's angles), and
    the motor speed ``omega`` (rad/s, signed; 0 where unknown) of every valid beam."""

    l: FloatArray
    alpha: FloatArray
    beta: FloatArray
    omega: FloatArray
    source: str = ""

    def __post_init__(self) -> None:
        arrays = []
        for name in ("l", "alpha", "beta", "omega"):
            a = np.asarray(getattr(self, name), dtype=np.float64).ravel()
            arrays.append(a)
            object.__setattr__(self, name, a)
        n = arrays[0].size
        if any(a.size != n for a in arrays):
            raise CalibrationError(
                f"l, alpha, beta and omega must have one value per beam, got {[a.size for a in arrays]}"
            )
        if not all(np.all(np.isfinite(a)) for a in arrays):
            raise CalibrationError("observations must be finite (drop beams without an echo first)")
        if np.any(self.l <= 0):
            raise CalibrationError("ranges must be > 0 (drop beams without an echo first)")

    @classmethod
    def from_raw(
        cls, l: ArrayLike, alpha: ArrayLike, beta: ArrayLike, omega: ArrayLike | None = None, source: str = ""
    ) -> Observations:
        l_ = np.asarray(l, dtype=np.float64).ravel()
        w = np.zeros_like(l_) if omega is None else np.broadcast_to(np.asarray(omega, dtype=np.float64), l_.shape)
        return cls(l_, np.asarray(alpha, dtype=np.float64), np.asarray(beta, dtype=np.float64), w, source)

    @classmethod
    def from_points(cls, xyz: ArrayLike, p: float = kinematics.DEFAULT_P, source: str = "") -> Observations:
        """Back from a cloud mapped with the nominal Eq. 1 (rig at the origin, inner parameter ``p``)
        to its readings (:func:`lrms.kinematics.inverse` with ``half_turn``: the sweep stayed
        within beta = +-90 deg); the motor speed is unknown (0)."""
        pts = np.asarray(xyz, dtype=np.float64)
        if pts.ndim != 2 or pts.shape[1] != 3:
            raise CalibrationError(f"a cloud must have shape (N, 3), got {pts.shape}")
        l, a, b = kinematics.inverse(pts, p, half_turn=True)
        keep = l > 0
        return cls.from_raw(l[keep], a[keep], b[keep], None, source)

    def __len__(self) -> int:
        return int(self.l.size)

    def subset(self, idx: NDArray[np.intp]) -> Observations:
        return Observations(self.l[idx], self.alpha[idx], self.beta[idx], self.omega[idx], self.source)


def concatenate(sweeps: Sequence[Observations]) -> tuple[Observations, NDArray[np.intp]]:
    """All sweeps as one set of observations, and the sweep index of each beam."""
    if not sweeps:
        raise CloudTooSmallError("no sweeps given")
    obs = Observations(
        np.concatenate([s.l for s in sweeps]),
        np.concatenate([s.alpha for s in sweeps]),
        np.concatenate([s.beta for s in sweeps]),
        np.concatenate([s.omega for s in sweeps]),
        ",".join(s.source for s in sweeps if s.source),
    )
    which = np.concatenate([np.full(len(s), i, dtype=np.intp) for i, s in enumerate(sweeps)])
    return obs, which


@dataclass(frozen=True)
class SphereSpec:
    """One reference sphere: its calibrated diameter and that diameter's standard uncertainty (m)."""

    diameter_m: float
    u_diameter_m: float = DEFAULT_U_DIAMETER


@dataclass(frozen=True)
class DistanceSpec:
    """A known centre-to-centre distance between spheres ``a`` and ``b`` (indices into the spheres)."""

    a: int
    b: int
    distance_m: float
    u_distance_m: float = DEFAULT_U_DISTANCE


@dataclass(frozen=True)
class Artefact:
    """What the calibration sweeps saw: planes of a room (target-free), reference spheres of known
    diameters at unknown positions, and known centre distances (a sphere bar).

    JSON (``lrms calibrate --artefact``): ``{"planes": true, "spheres": [{"diameter_m": 0.2,
    "u_diameter_m": 5e-6}, ...], "distances_m": [{"a": 0, "b": 1, "distance_m": 1.0,
    "u_distance_m": 1e-5}]}``; everything but ``planes`` is optional, uncertainties default to
    5 um (diameters) and 10 um (distances).
    """

    planes: bool = True
    spheres: tuple[SphereSpec, ...] = field(default_factory=tuple)
    distances: tuple[DistanceSpec, ...] = field(default_factory=tuple)

    def __post_init__(self) -> None:
        for i, s in enumerate(self.spheres):
            if not (np.isfinite(s.diameter_m) and s.diameter_m > 0):
                raise ArtefactError(f"sphere {i}: diameter must be a positive length in m, got {s.diameter_m}")
            if not (np.isfinite(s.u_diameter_m) and s.u_diameter_m > 0):
                raise ArtefactError(f"sphere {i}: u_diameter_m must be > 0, got {s.u_diameter_m}")
        seen: set[tuple[int, int]] = set()
        for j, d in enumerate(self.distances):
            n = len(self.spheres)
            if not (0 <= d.a < n and 0 <= d.b < n) or d.a == d.b:
                raise ArtefactError(f"distance {j}: spheres a={d.a}, b={d.b} must be two different of the {n} spheres")
            if not (np.isfinite(d.distance_m) and d.distance_m > 0):
                raise ArtefactError(f"distance {j}: distance_m must be a positive length, got {d.distance_m}")
            if not (np.isfinite(d.u_distance_m) and d.u_distance_m > 0):
                raise ArtefactError(f"distance {j}: u_distance_m must be > 0, got {d.u_distance_m}")
            key = (min(d.a, d.b), max(d.a, d.b))
            if key in seen:
                raise ArtefactError(f"distance {j}: spheres {key} already have a distance")
            seen.add(key)
        if not self.planes and not self.spheres:
            raise ArtefactError("an artefact needs planes or spheres")

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> Artefact:
        """From the JSON form (see the class docstring); anything unexpected is an :class:`ArtefactError`."""
        if not isinstance(data, Mapping):
            raise ArtefactError("an artefact is a JSON object")
        unknown = set(data) - {"planes", "spheres", "distances_m"}
        if unknown:
            raise ArtefactError(f"unknown artefact key(s): {', '.join(sorted(unknown))}")
        planes = data.get("planes", True)
        if not isinstance(planes, bool):
            raise ArtefactError(f"'planes' must be true or false, got {planes!r}")
        spheres = [_spec(SphereSpec, s, f"spheres[{i}]") for i, s in enumerate(_list(data, "spheres"))]
        distances = [_spec(DistanceSpec, d, f"distances_m[{i}]") for i, d in enumerate(_list(data, "distances_m"))]
        return cls(planes, tuple(spheres), tuple(distances))

    def to_dict(self) -> dict[str, Any]:
        return {
            "planes": self.planes,
            "spheres": [{"diameter_m": s.diameter_m, "u_diameter_m": s.u_diameter_m} for s in self.spheres],
            "distances_m": [
                {"a": d.a, "b": d.b, "distance_m": d.distance_m, "u_distance_m": d.u_distance_m} for d in self.distances
            ],
        }


def _list(data: Mapping[str, Any], key: str) -> list[Any]:
    v = data.get(key, [])
    if not isinstance(v, list):
        raise ArtefactError(f"'{key}' must be a list")
    return v


def _spec(kind: type[Any], item: Any, where: str) -> Any:
    if not isinstance(item, Mapping):
        raise ArtefactError(f"{where} must be an object")
    names = {f for f in kind.__dataclass_fields__}
    unknown = set(item) - names
    if unknown:
        raise ArtefactError(f"{where}: unknown key(s) {', '.join(sorted(unknown))} (known: {', '.join(sorted(names))})")
    try:
        values = {
            k: (int(v) if k in ("a", "b") else float(v))
            for k, v in item.items()
            if not isinstance(v, bool) and (k not in ("a", "b") or float(v).is_integer())
        }
    except (TypeError, ValueError):
        raise ArtefactError(f"{where}: values must be numbers") from None
    if len(values) != len(item):
        raise ArtefactError(f"{where}: values must be numbers (indices whole numbers)")
    try:
        return kind(**values)
    except TypeError as exc:
        raise ArtefactError(f"{where}: {exc}") from None
