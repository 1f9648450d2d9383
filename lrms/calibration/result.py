"""The outcome of a rig calibration, as plain data with a JSON form (for files and the result store)."""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from lrms.calibration.data import CalibrationError
from lrms.cylinder.footprint import LMS1XX_DIVERGENCE, LMS1XX_EXIT_DIAMETER, BeamOptics
from lrms.kinematics import RigModel

_log = logging.getLogger("lrms.calibration")

FloatArray = NDArray[np.float64]
SCHEMA = "lrms.calibration/1"


@dataclass(frozen=True)
class SurfaceFit:
    """One adjusted surface: ``kind`` "plane" (``params`` = unit normal, offset ``n . x = d``) or
    "sphere" (``params`` = centre, diameter); points used and rms residual (m)."""

    kind: str
    params: tuple[float, ...]
    points: int
    rms_m: float
    artefact_index: int = -1

    def to_dict(self) -> dict[str, Any]:
        d: dict[str, Any] = {"kind": self.kind, "points": self.points, "rms_m": self.rms_m}
        if self.kind == "plane":
            d.update(normal=list(self.params[:3]), offset_m=self.params[3])
        else:
            d.update(center_m=list(self.params[:3]), diameter_m=self.params[3], artefact_index=self.artefact_index)
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> SurfaceFit:
        if d["kind"] == "plane":
            params = (*map(float, d["normal"]), float(d["offset_m"]))
        else:
            params = (*map(float, d["center_m"]), float(d["diameter_m"]))
        return cls(str(d["kind"]), params, int(d["points"]), float(d["rms_m"]), int(d.get("artefact_index", -1)))


@dataclass(frozen=True)
class PoseFit:
    """The adjusted pose of one sweep (``--poses separate``): ``world_from_rig`` (4x4; the world is
    the first sweep's rig frame, whose pose is the identity and held) and the standard deviations
    of its rotation about the world's x, y, z (rad) and of its translation (m), zero for the first."""

    sweep: int
    world_from_rig: FloatArray
    std: tuple[float, ...] = (0.0,) * 6
    source: str = ""

    def to_dict(self) -> dict[str, Any]:
        return {
            "sweep": self.sweep,
            "source": self.source,
            "world_from_rig": np.asarray(self.world_from_rig).tolist(),
            "std_rotation_rad": list(self.std[:3]),
            "std_translation_m": list(self.std[3:]),
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> PoseFit:
        t = np.asarray(d["world_from_rig"], dtype=np.float64)
        if t.shape != (4, 4):
            raise ValueError(f"a pose's world_from_rig is 4x4, got {t.shape}")
        std = tuple(float(x) for x in [*d.get("std_rotation_rad", [0.0] * 3), *d.get("std_translation_m", [0.0] * 3)])
        return cls(int(d["sweep"]), t, std, str(d.get("source", "")))


@dataclass(frozen=True)
class Identifiability:
    """What the data could determine.

    ``held``: parameters held at their nominal values, with the reason and the data that would
    determine them; ``rank`` and ``condition``: of the normal matrix of the rig parameters
    (surfaces eliminated, columns scaled by the parameters' tolerance spreads) over the
    estimated ones (``inf`` when singular; ``null`` in JSON, which has no infinity); ``weak``:
    estimated parameters whose standard deviation exceeds their goal,
    with advice; ``eigenvalues``: of the scaled matrix over all non-structural parameters,
    ascending (1 / eigenvalue = variance in units of the spread).
    """

    held: dict[str, str]
    rank: int
    condition: float
    weak: dict[str, str] = field(default_factory=dict)
    eigenvalues: tuple[float, ...] = ()

    def to_dict(self) -> dict[str, Any]:
        return {
            "held": dict(self.held),
            "rank": self.rank,
            "condition": self.condition if np.isfinite(self.condition) else None,
            "weak": dict(self.weak),
            "eigenvalues": list(self.eigenvalues),
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> Identifiability:
        return cls(
            dict(d["held"]), int(d["rank"]), float("inf") if d["condition"] is None else float(d["condition"]),
            dict(d.get("weak", {})),
            tuple(float(x) for x in d.get("eigenvalues", ())),
        )  # fmt: skip


@dataclass(frozen=True)
class CalibrationResult:
    """A rig calibration: the estimated :class:`RigModel`, the covariance of its parameters (SI, in
    :attr:`RigModel.NAMES` order; rows and columns of held parameters are zero), the adjusted
    surfaces, the residual summary and the identifiability report."""

    model: RigModel
    nominal: RigModel
    covariance: FloatArray
    estimated: tuple[str, ...]
    identifiability: Identifiability
    surfaces: tuple[SurfaceFit, ...]
    residuals: dict[str, float]
    artefact: dict[str, Any]
    sources: tuple[str, ...] = ()
    created: str = ""
    software_version: str = ""
    #: One per sweep when the sweeps were adjusted with separate poses (empty: one shared pose).
    poses: tuple[PoseFit, ...] = ()
    #: The scanner's spot scale from the spheres, ``{"spot_scale": s, "spot_scale_u": u,
    #: "exit_diameter_m", "divergence_rad", "profile_sigma", "extent", "assumed_scale"}``: ``s``
    #: multiplies the nominal spot (exit diameter, divergence, the Gaussian's sigma over the
    #: diameter, the disc of ``extent`` spot radii its light is cut to) it was estimated against,
    #: stored with it (``extent`` absent in older files: those were estimated with an endless
    #: Gaussian, and :meth:`beam_optics` refuses them); ``assumed_scale`` is the
    #: scale the final adjustment of the rig used (differs from ``s`` by more than 2 ``u`` when the
    #: second stage did not settle; absent in older files). ``None`` when not estimated (thin beam,
    #: no spheres).
    optics: dict[str, float] | None = None
    #: With a finite spot (``CalibrationOptions.optics``): beams left out of the adjustment because
    #: their spot was not wholly on their surface, by surface ("plane k", "sphere i": the artefact's
    #: sphere i); ``None`` for the thin beam.
    censored: dict[str, int] | None = None

    def __post_init__(self) -> None:
        cov = np.asarray(self.covariance, dtype=np.float64)
        n = len(RigModel.NAMES)
        if cov.shape != (n, n):
            raise CalibrationError(f"a calibration covariance is {n}x{n}, got {cov.shape}")
        object.__setattr__(self, "covariance", cov)

    def std(self) -> dict[str, float]:
        """Standard deviations (SI) of the estimated parameters."""
        idx = {n: i for i, n in enumerate(RigModel.NAMES)}
        return {n: float(np.sqrt(max(self.covariance[idx[n], idx[n]], 0.0))) for n in self.estimated}

    def correlations(self) -> FloatArray:
        """Correlation matrix over :attr:`estimated` (in that order)."""
        idx = [RigModel.NAMES.index(n) for n in self.estimated]
        c = self.covariance[np.ix_(idx, idx)]
        s = np.sqrt(np.clip(np.diag(c), 1e-300, None))
        return np.asarray(c / np.outer(s, s), dtype=np.float64)

    def table(self) -> list[dict[str, Any]]:
        """One row per parameter in display units: value, nominal, std (None when held)."""
        std = self.std()
        rows = []
        for name in RigModel.NAMES:
            unit, f = RigModel.UNITS[name]
            rows.append(
                {
                    "name": name,
                    "unit": unit,
                    "value": getattr(self.model, name) * f,
                    "nominal": getattr(self.nominal, name) * f,
                    "std": std[name] * f if name in std else None,
                    "held": name in self.identifiability.held,
                }
            )
        return rows

    def to_dict(self) -> dict[str, Any]:
        return {
            "schema": SCHEMA,
            "created": self.created,
            "software_version": self.software_version,
            "model": self.model.to_dict(),
            "nominal": self.nominal.to_dict(),
            "estimated": list(self.estimated),
            "covariance": self.covariance.tolist(),
            "correlations": self.correlations().tolist(),
            "std": self.std(),
            "identifiability": self.identifiability.to_dict(),
            "surfaces": [s.to_dict() for s in self.surfaces],
            "residuals": dict(self.residuals),
            "artefact": self.artefact,
            "sources": list(self.sources),
            "table": self.table(),
            **({"poses": [p.to_dict() for p in self.poses]} if self.poses else {}),
            **({"optics": dict(self.optics)} if self.optics is not None else {}),
            **({"censored": dict(self.censored)} if self.censored is not None else {}),
        }

    def beam_optics(self, nominal: Any) -> Any:
        """``nominal`` (a :class:`lrms.cylinder.BeamOptics`) with this calibration's spot scale
        applied: exit diameter and divergence are ``s`` x the nominal spot the scale was estimated
        against (``optics["exit_diameter_m"]``, ``optics["divergence_rad"]``, with the spot profile
        ``optics["profile_sigma"]`` and its light cut to ``optics["extent"]`` spot radii),
        ``spot_scale_u`` the relative uncertainty of the spot size, ``u / s``. ``nominal`` itself
        when the calibration has no spot scale or ``nominal`` is ``None`` (thin beam). Raises
        :class:`CalibrationError` when ``nominal``'s exit diameter, divergence, profile sigma or
        extent differs from the calibration's (the scale is relative to that spot and would be
        applied to another). An older calibration without ``extent`` (its scale estimated with an
        endless Gaussian spot, while the fit's spot ends) is applied with a logged warning and
        :data:`ENDLESS_SCALE_U` more relative uncertainty in quadrature (a systematic shift not
        corrected is carried as uncertainty; recalibrating removes it)."""
        if self.optics is None or nominal is None:
            return nominal
        import dataclasses
        import math

        o = self.optics
        for key in ("exit_diameter_m", "divergence_rad", "profile_sigma"):
            if not math.isclose(getattr(nominal, key), o[key], rel_tol=1e-9, abs_tol=1e-12):
                raise CalibrationError(
                    f"the calibration's spot scale is relative to the nominal spot {key} {o[key]:.6g}, "
                    f"but the fit's optics give {getattr(nominal, key):.6g}: use the calibration's nominal spot "
                    f"(exit {o['exit_diameter_m'] * 1e3:.6g} mm, divergence {o['divergence_rad'] * 1e3:.6g} mrad,"
                    f" profile sigma {o['profile_sigma']:.6g})"
                )
        extra_u = 0.0
        if "extent" not in o:  # an older file: applied, its model's shift carried as uncertainty
            extra_u = ENDLESS_SCALE_U
            _log.warning(
                "the calibration's spot scale %.4g was estimated with an endless Gaussian spot (a file without "
                "the optics' extent); the fit's spot ends at %.3g spot radii, under which such scales read "
                "1.6-2.6 %% low: applied with %.0f %% more relative uncertainty in quadrature; recalibrate",
                o["spot_scale"], nominal.extent, 100 * ENDLESS_SCALE_U,
            )  # fmt: skip
        elif not math.isclose(nominal.extent, o["extent"], rel_tol=1e-9):
            raise CalibrationError(
                f"the calibration's spot scale is relative to a spot cut at extent {o['extent']:.6g} spot radii, "
                f"but the fit's optics give extent {nominal.extent:.6g}: use the calibration's extent"
            )
        s, u = o["spot_scale"], o["spot_scale_u"]
        return dataclasses.replace(
            nominal,
            exit_diameter_m=o["exit_diameter_m"] * s,
            divergence_rad=o["divergence_rad"] * s,
            spot_scale_u=min(float(np.hypot(u / s, extra_u)), 1.0),
        )

    def to_json(self, indent: int | None = 2) -> str:
        return json.dumps(self.to_dict(), indent=indent)

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> CalibrationResult:
        if not isinstance(d, dict) or d.get("schema") != SCHEMA:
            raise CalibrationError(f"not a calibration (expected schema {SCHEMA!r})")
        try:
            return cls(
                model=RigModel.from_dict(d["model"]),
                nominal=RigModel.from_dict(d["nominal"]),
                covariance=np.asarray(d["covariance"], dtype=np.float64),
                estimated=tuple(str(n) for n in d["estimated"]),
                identifiability=Identifiability.from_dict(d["identifiability"]),
                surfaces=tuple(SurfaceFit.from_dict(s) for s in d["surfaces"]),
                residuals={k: float(v) for k, v in d["residuals"].items()},
                artefact=dict(d["artefact"]),
                sources=tuple(str(s) for s in d.get("sources", ())),
                created=str(d.get("created", "")),
                software_version=str(d.get("software_version", "")),
                poses=tuple(PoseFit.from_dict(p) for p in d.get("poses", ())),
                optics=_optics(d.get("optics")),
                censored=None if d.get("censored") is None else {str(k): int(v) for k, v in d["censored"].items()},
            )
        except (KeyError, TypeError, ValueError) as exc:
            raise CalibrationError(f"malformed calibration: {exc}") from None

    @classmethod
    def from_json(cls, text: str) -> CalibrationResult:
        try:
            data = json.loads(text)
        except json.JSONDecodeError as exc:
            raise CalibrationError(f"a calibration file is JSON: {exc}") from None
        return cls.from_dict(data)


#: The Gaussian's sigma over the spot diameter the fit's optics assume by default (older files were
#: estimated against it).
_LMS1XX_PROFILE_SIGMA = BeamOptics().profile_sigma
#: Relative uncertainty added to the spot scale of an older calibration (no ``extent``: estimated
#: with an endless Gaussian spot): the disc-cut echo moved such estimates up by 1.6-2.6 %
#: (docs/calibration.md, bench/bench_spot_scale_disc.py), so 3 % covers the shift.
ENDLESS_SCALE_U = 0.03


def _optics(d: Any) -> dict[str, float] | None:
    """The ``optics`` entry checked; a file without the nominal spot (older files) gets the LMS1xx
    defaults it was estimated against; one without ``extent`` keeps none (an endless Gaussian)."""
    if d is None:
        return None
    s, u = float(d["spot_scale"]), float(d["spot_scale_u"])
    if not (np.isfinite(s) and s > 0 and np.isfinite(u) and u >= 0):
        raise ValueError(f"optics: spot_scale must be > 0 and spot_scale_u >= 0, got {s}, {u}")
    out = {
        "spot_scale": s,
        "spot_scale_u": u,
        "exit_diameter_m": float(d.get("exit_diameter_m", LMS1XX_EXIT_DIAMETER)),
        "divergence_rad": float(d.get("divergence_rad", LMS1XX_DIVERGENCE)),
        "profile_sigma": float(d.get("profile_sigma", _LMS1XX_PROFILE_SIGMA)),
    }
    if not (0 <= out["exit_diameter_m"] <= 0.5 and 0 <= out["divergence_rad"] <= 0.5):
        raise ValueError(
            f"optics: exit_diameter_m and divergence_rad must be within [0, 0.5], "
            f"got {out['exit_diameter_m']}, {out['divergence_rad']}"
        )
    if not (np.isfinite(out["profile_sigma"]) and 0 < out["profile_sigma"] <= 10):
        raise ValueError(f"optics: profile_sigma must be within (0, 10], got {out['profile_sigma']}")
    if out["exit_diameter_m"] == 0 and out["divergence_rad"] == 0:
        raise ValueError("optics: the nominal spot must not be of zero size")
    if d.get("extent") is not None:  # absent: an older file, estimated with an endless Gaussian
        e = float(d["extent"])
        if not (np.isfinite(e) and 0.1 <= e <= 10):
            raise ValueError(f"optics: extent must be within [0.1, 10] spot radii, got {e}")
        out["extent"] = e
    if d.get("assumed_scale") is not None:
        a = float(d["assumed_scale"])
        if not (np.isfinite(a) and a > 0):
            raise ValueError(f"optics: assumed_scale must be > 0, got {a}")
        out["assumed_scale"] = a
    return out
