"""GUM uncertainty budget of a fitted diameter: one row per source, root-sum-square, U = k u_c.

Every row states the standard uncertainty ``u_x`` of one input quantity (with its unit), the
sensitivity ``c`` of the diameter to it (m per unit) and its contribution ``u_m = |c| u_x``
(JCGM 100, 5.1.3). The inputs are taken as uncorrelated, so ``u_c = sqrt(sum u_m^2)``; the
expanded uncertainty is ``U = k u_c`` with ``k = 2`` by default.

Sensitivities come from the data: the line-of-sight fit minimises ``sum ((l_i - t_i(theta)) /
s_i)^2`` (plus the miss terms of beams passing the model), so a small change ``dl`` of the
measured ranges moves the solution by ``dtheta = -(J^T J)^-1 J^T (dl / s)`` (the fit's normal
equations, linearised at the solution; ``J``: the whitened Jacobian). :func:`range_gains` gives
``g_i = d(diameter) / d(l_i)`` for every inlier beam; each systematic effect is a pattern of range
changes ``dl_i = a_i x`` per unit of its input ``x``:

* range offset ``k0``: ``a_i = 1``; range scale ``k1``: ``a_i = l_i``; temperature: the range
  drift per kelvin times 1;
* an error ``e`` of a beam's scan angle (alpha) or of the motor angle (beta): the echo comes
  from the beam at ``angle + e`` while the fit uses the reported angle, so the fit's residuals
  change by ``(dt_i / d angle) e / s_i`` in the range row and ``-(d gap_i / d angle) e /
  sigma_perp_i`` in the miss row (:func:`angle_gains`; ``t_i``: the range where the beam meets
  the fitted cylinder, ``gap_i``: how far a passing beam misses it; central differences). A
  rotation about the motor shaft (a motor-zero error) gives ``c = 0`` to rounding (tested).

With ``c_i`` the diameter's change per unit input on beam ``i``, a common input (offset, scale,
alpha zero) gives ``c = sum_i c_i``; an input drawn
independently per beam (the noise of alpha and beta beyond the fit's range-only covariance) gives
``c = sqrt(sum_i c_i^2)``; an input drawn once per scan (motor timing jitter, encoder
quantisation: every beam of a scan shares its beta) gives ``c = sqrt(sum_scans (sum_(i in scan)
c_i)^2)``. The fit's own row (type A) is its covariance's ``u(d)``. Rows given as a diameter
contribution (the footprint / edge model's ``fit.extra["edge_model_u_m"]``: 0 when the footprint
fit estimated the spot's size, whose uncertainty is then in the fit's row; the edge family's
``fit.extra["edge_family_u_m"]`` (model choice, Akaike-weighted spread), a calibration's
covariance through :class:`CalibrationInput`, ``extra_rows``) enter as they are.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from lrms import kinematics
from lrms.covariance import NoiseModel
from lrms.errors import FitError, LrmsError

if TYPE_CHECKING:
    # lrms.cylinder (scipy.optimize, tenths of a second) is imported where a fit is at hand: the
    # rig config reads this module's defaults and must not pay for it (docs/architecture.md)
    from lrms.cylinder import CylinderFit, Rays

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]

Distribution = Literal["rectangular", "normal"]
DISTRIBUTIONS: tuple[str, ...] = ("rectangular", "normal")

#: SICK, knowledge base "Measurement errors LMSxxx" (docs/cylinder.md, section 3.1): systematic range
#: error of an LMS1xx +-30 mm typical (+-40 mm max), temperature dependent, no distribution given.
LMS1XX_SYSTEMATIC_HALF_WIDTH = 0.030
#: Its standard uncertainty as a rectangular distribution of half-width 30 mm (JCGM 100, 4.3.7).
LMS1XX_RANGE_OFFSET_U = LMS1XX_SYSTEMATIC_HALF_WIDTH / float(np.sqrt(3.0))
#: Encoder quantisation of the default drive (10000 counts per motor revolution, gear 50: one count
#: 7.2e-4 deg at the output shaft), as a rectangular distribution of one count: q / sqrt(12).
DEFAULT_ENCODER_U = float(2.0 * np.pi / (10_000 * 50) / np.sqrt(12.0))
#: Our estimate of the per-scan timing error between a scan and the motor angle interpolated for it
#: (docs/service.md: the clock model's envelope, motor samples stamped by the host at 200 Hz;
#: millisecond delays seen on a loaded host): 1 ms.
DEFAULT_TIMING_JITTER_U = 1e-3
#: Our estimate of the mounting error of the scanner's zero direction and of the motor's zero,
#: uncalibrated: 0.1 deg each.
DEFAULT_ZERO_U = float(np.deg2rad(0.1))
#: Step (rad) of the central differences of a beam's range with respect to its angles.
_ANGLE_STEP = 1e-6


def _nonneg(name: str, v: float) -> float:
    x = float(v)
    if not np.isfinite(x) or x < 0:
        raise LrmsError(f"{name} must be a finite standard uncertainty >= 0, got {v!r}")
    return x


@dataclass(frozen=True)
class SensorErrors:
    """Type-B inputs of the budget, as standard uncertainties (SI; the scale in ppm).

    Defaults are an uncalibrated LMS1xx on the default drive (docs/cylinder.md, "The budget"):

    * ``range_offset_u_m``: SICK's +-30 mm typical systematic error as a rectangular distribution
      (17.3 mm). SICK bounds the total systematic error, not its parts, so it is carried here;
    * ``range_scale_u_ppm``: 0 (SICK publishes no scale term; at one range a scale error is an
      offset, and the +-30 mm bound holds over the whole range, so a default scale term would count
      the same error twice). Set it with a calibration that separates offset and scale;
    * ``temperature_coeff_m_per_k`` x ``temperature_u_k``: the range drift per kelvin (0: SICK's
      bound already covers the temperature dependence; a calibrated rig states its drift);
    * ``alpha_zero_u_rad``, ``beta_zero_u_rad``: zero errors of the scan angle and the motor angle
      (ours: 0.1 deg, uncalibrated);
    * ``encoder_u_rad``: the motor angle's quantisation per scan (one count, rectangular);
    * ``timing_jitter_u_s``: the per-scan error of the time at which the motor angle is read for a
      scan (ours: 1 ms), times the motor speed.
    """

    range_offset_u_m: float = LMS1XX_RANGE_OFFSET_U
    range_offset_distribution: Distribution = "rectangular"
    range_scale_u_ppm: float = 0.0
    range_scale_distribution: Distribution = "normal"
    temperature_coeff_m_per_k: float = 0.0
    temperature_u_k: float = 5.0
    alpha_zero_u_rad: float = DEFAULT_ZERO_U
    beta_zero_u_rad: float = DEFAULT_ZERO_U
    encoder_u_rad: float = DEFAULT_ENCODER_U
    timing_jitter_u_s: float = DEFAULT_TIMING_JITTER_U

    def __post_init__(self) -> None:
        for name in (
            "range_offset_u_m",
            "range_scale_u_ppm",
            "temperature_u_k",
            "alpha_zero_u_rad",
            "beta_zero_u_rad",
            "encoder_u_rad",
            "timing_jitter_u_s",
        ):
            object.__setattr__(self, name, _nonneg(name, getattr(self, name)))
        c = float(self.temperature_coeff_m_per_k)
        if not np.isfinite(c):
            raise LrmsError(f"temperature_coeff_m_per_k must be finite, got {self.temperature_coeff_m_per_k!r}")
        for name in ("range_offset_distribution", "range_scale_distribution"):
            if getattr(self, name) not in DISTRIBUTIONS:
                raise LrmsError(f"{name} must be one of {', '.join(DISTRIBUTIONS)}, got {getattr(self, name)!r}")

    @classmethod
    def none(cls) -> SensorErrors:
        """No systematic effects at all (the seed's model: range and angle noise only)."""
        return cls(
            range_offset_u_m=0.0,
            alpha_zero_u_rad=0.0,
            beta_zero_u_rad=0.0,
            encoder_u_rad=0.0,
            timing_jitter_u_s=0.0,
        )


@dataclass(frozen=True)
class BudgetRow:
    """One source: ``u_m = |c| u_x`` (m), ``u_x`` in ``unit``, ``c`` in m per ``unit``."""

    source: str
    type: Literal["A", "B"]
    u_x: float
    unit: str
    c: float
    u_m: float
    distribution: str
    note: str = ""

    def __post_init__(self) -> None:
        for name in ("u_x", "u_m"):
            _nonneg(f"{self.source}: {name}", getattr(self, name))
        if not np.isfinite(self.c):
            raise LrmsError(f"{self.source}: sensitivity must be finite, got {self.c!r}")
        if self.type not in ("A", "B"):
            raise LrmsError(f"{self.source}: type must be 'A' or 'B', got {self.type!r}")

    @classmethod
    def of(
        cls, source: str, type_: Literal["A", "B"], u_x: float, unit: str, c: float, distribution: str, note: str = ""
    ) -> BudgetRow:
        """A row whose contribution is ``|c| u_x``."""
        ux = _nonneg(f"{source}: u_x", u_x)
        return cls(source, type_, ux, unit, float(c), abs(float(c)) * ux, distribution, note)

    def to_dict(self) -> dict[str, Any]:
        return {
            "source": self.source,
            "type": self.type,
            "u_x": float(self.u_x),
            "unit": self.unit,
            "c": float(self.c),
            "u_m": float(self.u_m),
            "distribution": self.distribution,
            "note": self.note,
        }


@dataclass(frozen=True)
class CalibrationInput:
    """A calibration's contribution (the hook for a later calibration): the covariance of its
    parameters ``covariance`` (n x n, in ``units``) and the diameter's sensitivity to each
    ``sensitivity`` (m per unit, e.g. from :func:`range_gains` or a refit). One row, correlations
    kept: ``u_m = sqrt(c^T V c)``. ``replaces``: sources of the uncalibrated budget this
    calibration supersedes (e.g. ``("range offset",)``); those rows are left out."""

    names: tuple[str, ...]
    covariance: FloatArray
    sensitivity: FloatArray
    units: tuple[str, ...] = ()
    replaces: tuple[str, ...] = ()
    note: str = ""

    def __post_init__(self) -> None:
        n = len(self.names)
        cov = np.asarray(self.covariance, dtype=np.float64)
        c = np.asarray(self.sensitivity, dtype=np.float64).reshape(-1)
        if n == 0 or cov.shape != (n, n) or c.shape != (n,):
            raise LrmsError(f"calibration: {n} names need an {n} x {n} covariance and {n} sensitivities")
        if not (np.all(np.isfinite(cov)) and np.all(np.isfinite(c))):
            raise LrmsError("calibration: covariance and sensitivities must be finite")
        if not np.allclose(cov, cov.T, rtol=1e-9, atol=1e-300) or np.min(np.linalg.eigvalsh(cov)) < -1e-12 * max(
            float(np.max(np.abs(cov))), 1e-300
        ):
            raise LrmsError("calibration: covariance must be symmetric positive semi-definite")
        if self.units and len(self.units) != n:
            raise LrmsError("calibration: one unit per parameter")
        object.__setattr__(self, "covariance", cov)
        object.__setattr__(self, "sensitivity", c)

    def row(self) -> BudgetRow:
        var = float(self.sensitivity @ self.covariance @ self.sensitivity)
        u = float(np.sqrt(max(var, 0.0)))
        return BudgetRow(
            source="calibration",
            type="B",
            u_x=u,
            unit="m",
            c=1.0,
            u_m=u,
            distribution="normal",
            note=self.note or f"parameters {', '.join(self.names)}: sqrt(c^T V c), correlations kept",
        )


@dataclass(frozen=True)
class Budget:
    """The rows, ``u_c`` (root-sum-square: the inputs are uncorrelated), ``U = k u_c``."""

    rows: tuple[BudgetRow, ...]
    k: float = 2.0
    correlation: str = "inputs uncorrelated: u_c = sqrt(sum u_m^2)"

    def __post_init__(self) -> None:
        kk = float(self.k)
        if not np.isfinite(kk) or kk <= 0:
            raise LrmsError(f"coverage factor k must be > 0, got {self.k!r}")

    @property
    def combined(self) -> float:
        return float(np.sqrt(sum(r.u_m * r.u_m for r in self.rows)))

    @property
    def expanded(self) -> float:
        return float(self.k) * self.combined

    def row(self, source: str) -> BudgetRow:
        for r in self.rows:
            if r.source == source:
                return r
        raise KeyError(source)

    def diameter_u_beyond(self, sources: Sequence[str]) -> float:
        """Root-sum-square of the rows not in ``sources``."""
        return float(np.sqrt(sum(r.u_m * r.u_m for r in self.rows if r.source not in sources)))

    def to_dict(self) -> dict[str, Any]:
        """``budget`` (rows), ``combined_m``, ``expanded_m``, ``k``, ``correlation``."""
        return {
            "budget": [r.to_dict() for r in self.rows],
            "combined_m": self.combined,
            "expanded_m": self.expanded,
            "k": float(self.k),
            "correlation": self.correlation,
        }


# --------------------------------------------------------------------------- sensitivities


def _weights(fit: CylinderFit, rays: Rays) -> FloatArray:
    """The per-beam sigmas the fit was weighted with (grazing weights when it carries them)."""
    lat = fit.extra.get("grazing_sigma_m", 0.0)
    if lat > 0:
        from lrms.cylinder import grazing_sigmas

        return grazing_sigmas(fit.cylinder, rays, lat)
    return np.asarray(np.broadcast_to(rays.sigma_l, rays.ranges.shape), dtype=np.float64)


def _gain_rows(fit: CylinderFit, rays: Rays) -> tuple[FloatArray, FloatArray, FloatArray]:
    """``d(diameter) / d(r_k)`` for the fit's whitened residual rows (range rows, miss rows) and the
    range rows' sigmas, from the normal equations: ``dtheta = -(J^T J)^-1 J^T dr``."""
    from lrms.cylinder import _Frame, los_jacobian

    if not fit.line_of_sight:
        raise FitError("range sensitivities are defined for a line-of-sight fit")
    n = fit.inliers.size
    if rays.ranges.shape[0] != n:
        raise FitError("one beam per inlier is needed for the range sensitivities")
    cyl = fit.cylinder
    frame = _Frame(cyl.point, cyl.direction, fit.frame[0], fit.frame[1], cyl.radius)
    sig = _weights(fit, rays)
    jac = los_jacobian(np.zeros(5), frame, rays.origins, rays.dirs, sig, rays.sigma_perp)
    try:
        sol = np.linalg.solve(jac.T @ jac, jac.T)  # (5, 2n)
    except np.linalg.LinAlgError as exc:  # pragma: no cover - degenerate geometry
        raise FitError("cylinder fit is degenerate (singular normal matrix)") from exc
    g = -2.0 * sol[4]
    return np.asarray(g[:n], dtype=np.float64), np.asarray(g[n:], dtype=np.float64), sig


def range_gains(fit: CylinderFit, rays: Rays) -> FloatArray:
    """``d(diameter) / d(l_i)`` for every inlier beam (``rays``: one per inlier) of a line-of-sight
    fit, from its normal equations at the solution: ``dtheta = -(J^T J)^-1 J^T (dl / s)``."""
    g_range, _, sig = _gain_rows(fit, rays)
    return np.asarray(g_range / sig, dtype=np.float64)


def angle_gains(
    fit: CylinderFit, rays: Rays, alpha: ArrayLike, beta: ArrayLike, p: float
) -> tuple[FloatArray, FloatArray]:
    """``d(diameter) / d(e_i)`` for an error ``e_i`` of beam ``i``'s scan angle (first array) and
    motor angle (second): the echo comes from the beam at ``angle + e_i`` while the fit uses the
    reported angle. To first order the fit's residuals change by ``(dt_i / d angle) e_i / s_i`` in
    the range row and ``-(d gap_i / d angle) e_i / sigma_perp_i`` in the miss row (``t``: the range
    where the beam meets the fitted cylinder, ``gap``: how far a passing beam misses it; central
    differences), and the solution by the normal equations' response to that."""
    a = np.asarray(alpha, dtype=np.float64).reshape(-1)
    b = np.asarray(beta, dtype=np.float64).reshape(-1)
    if a.shape != b.shape or a.shape != rays.ranges.shape:
        raise FitError("one alpha and beta per inlier beam is needed")
    g_range, g_miss, sig = _gain_rows(fit, rays)
    cyl = fit.cylinder
    h = _ANGLE_STEP

    def cast(aa: FloatArray, bb: FloatArray) -> tuple[FloatArray, FloatArray]:
        o, d = kinematics.beam_rays(aa, bb, p)
        return cyl.ray_range(o, d)

    out = []
    for da, db in ((h, 0.0), (0.0, h)):
        tp, gp = cast(a + da, b + db)
        tm, gm = cast(a - da, b - db)
        dt, dgap = (tp - tm) / (2 * h), (gp - gm) / (2 * h)
        out.append(np.asarray(g_range * dt / sig - g_miss * dgap / rays.sigma_perp, dtype=np.float64))
    return out[0], out[1]


def scan_groups(beta: ArrayLike, tolerance: float = 1e-4) -> IntArray:
    """Scan index of every beam from its motor angle, for clouds that carry none: beams of one scan
    share beta (within its noise, 6e-7 rad on the seed's rig); scans of a sweep lie a motor step
    apart (0.4 deg at 10 deg/s and 25 Hz). Sorted betas split where they jump by > ``tolerance``."""
    b = np.asarray(beta, dtype=np.float64).reshape(-1)
    if b.size == 0:
        return np.zeros(0, dtype=np.intp)
    order = np.argsort(b, kind="stable")
    jumps = np.concatenate([[0], (np.diff(b[order]) > tolerance).astype(np.intp)])
    out = np.empty(b.size, dtype=np.intp)
    out[order] = np.cumsum(jumps)
    return out


def _per_scan_rss(x: FloatArray, scan: IntArray) -> float:
    _, inv = np.unique(scan, return_inverse=True)
    sums = np.bincount(inv.reshape(-1), weights=x)
    return float(np.sqrt(np.sum(sums * sums)))


#: Source names of the rows, in the order of the table.
SOURCES = (
    "fit (type A)",
    "range offset",
    "range scale",
    "temperature drift",
    "footprint / edge model",
    "edge family (model choice)",
    "footprint bias correction",
    "alpha zero",
    "alpha noise",
    "beta noise",
    "beta zero",
    "motor timing jitter",
    "motor encoder",
)


@dataclass(frozen=True)
class BeamGeometry:
    """What the budget needs of the inlier beams besides their rays: scan and motor angles (rad),
    the inner parameter ``p`` (m), the scan index of every beam (None: from beta by
    :func:`scan_groups`) and the motor speed (rad/s) during the sweep."""

    alpha: FloatArray
    beta: FloatArray
    p: float
    motor_speed_rad_s: float
    scan_index: IntArray | None = None

    def __post_init__(self) -> None:
        a = np.asarray(self.alpha, dtype=np.float64).reshape(-1)
        b = np.asarray(self.beta, dtype=np.float64).reshape(-1)
        if a.shape != b.shape:
            raise LrmsError("alpha and beta differ in length")
        v = float(self.motor_speed_rad_s)
        if not np.isfinite(v) or v < 0:
            raise LrmsError(f"motor speed must be finite and >= 0, got {self.motor_speed_rad_s!r}")
        object.__setattr__(self, "alpha", a)
        object.__setattr__(self, "beta", b)
        if self.scan_index is not None:
            s = np.asarray(self.scan_index).reshape(-1)
            if s.shape != a.shape:
                raise LrmsError("one scan index per beam")
            object.__setattr__(self, "scan_index", s.astype(np.intp))

    def scans(self) -> IntArray:
        return self.scan_index if self.scan_index is not None else scan_groups(self.beta)

    def subset(self, idx: ArrayLike) -> BeamGeometry:
        i = np.asarray(idx)
        s = None if self.scan_index is None else self.scan_index[i]
        return BeamGeometry(self.alpha[i], self.beta[i], self.p, self.motor_speed_rad_s, s)


@dataclass(frozen=True)
class Sensitivities:
    """The diameter's sensitivities to the budget's inputs (see the module notes)."""

    range_offset: float  # m per m
    range_scale_ppm: float  # m per ppm
    alpha_zero: float  # m per rad
    alpha_noise: float  # m per rad, rss over beams
    beta_noise: float  # m per rad, rss over beams
    beta_zero: float  # m per rad
    beta_per_scan: float  # m per rad, rss over scans
    gains: FloatArray = field(repr=False)  # d diameter / d l_i


def sensitivities(fit: CylinderFit, rays: Rays, beams: BeamGeometry) -> Sensitivities:
    """All sensitivities of a line-of-sight fit (``rays``, ``beams``: its inlier beams)."""
    g = range_gains(fit, rays)
    ga, gb = angle_gains(fit, rays, beams.alpha, beams.beta, beams.p)
    return Sensitivities(
        range_offset=float(np.sum(g)),
        range_scale_ppm=float(np.sum(g * rays.ranges)) * 1e-6,
        alpha_zero=float(np.sum(ga)),
        alpha_noise=float(np.sqrt(np.sum(ga * ga))),
        beta_noise=float(np.sqrt(np.sum(gb * gb))),
        beta_zero=float(np.sum(gb)),
        beta_per_scan=_per_scan_rss(gb, beams.scans()),
        gains=g,
    )


def _not_evaluated(name: str, why: str) -> BudgetRow:
    """A type-B row of zero uncertainty marked "not evaluated", ``why`` saying what is missing."""
    return BudgetRow(name, "B", 0.0, "m", 1.0, 0.0, "not evaluated", why)


def _edge_row(fit: CylinderFit) -> BudgetRow:
    u = fit.extra.get("edge_model_u_m")
    if u is None:
        return _not_evaluated(
            "footprint / edge model",
            "this fit has no edge model (thin-beam model): under a real LMS1xx's footprint it is biased by "
            "tens of mm, which no row here covers (docs/sensor-model.md)",
        )
    scale = fit.extra.get("edge_spot_scale")
    if fit.extra.get("edge_mode_first", 0.0) < 0:
        note = (
            "the thin beam won the model choice (Akaike criterion) over the footprint families: the reported"
            " fit has no spot, 0 here; the families' spread is the edge family row (fit.extra['edge_model_u_m'])"
        )
    elif scale is not None:
        # estimated by the fit: its uncertainty is in the fit's covariance, not carried again here
        note = (
            f"the spot's size estimated by the fit, {float(scale):.3f} +- {float(fit.extra['edge_spot_scale_u']):.3f}"
            " x the nominal (the nominal a prior): in the fit's type A row, 0 here (fit.extra['edge_model_u_m'])"
        )
    else:
        note = "the spot's size held at its nominal value, carried with its uncertainty (fit.extra['edge_model_u_m'])"
    return BudgetRow.of("footprint / edge model", "B", float(u), "m", 1.0, "normal", note)


def _family_row(fit: CylinderFit) -> BudgetRow:
    u = fit.extra.get("edge_family_u_m")
    if u is None:
        return _not_evaluated("edge family (model choice)", "no footprint fit: no choice among edge families was made")
    w = ", ".join(
        f"{k.removeprefix('akaike_weight_')} {v:.2g}"
        for k, v in sorted(fit.extra.items())
        if k.startswith("akaike_weight_")
    )
    return BudgetRow.of(
        "edge family (model choice)",
        "B",
        float(u),
        "m",
        1.0,
        "normal",
        "the families' diameters about the reported one, weighted by their Akaike weights"
        + (f" ({w})" if w else "")
        + " (fit.extra['edge_family_u_m'])",
    )


def _footprint_bias_row(fit: CylinderFit) -> BudgetRow:
    """The footprint fit's second-order (Box) bias correction, subtracted from the diameter: its own
    standard uncertainty (``fit.extra["footprint_bias_u_m"]``, lrms/cylinder/footprint_bias.py)."""
    if "footprint_bias_u_m" not in fit.extra:
        return _not_evaluated("footprint bias correction", "no footprint fit: no footprint bias correction was applied")
    corr = float(fit.extra.get("bias_correction_diameter_m", 0.0))
    return BudgetRow.of(
        "footprint bias correction",
        "B",
        float(fit.extra["footprint_bias_u_m"]),
        "m",
        1.0,
        "rectangular",
        f"Box's second-order noise bias of the footprint fit, {corr * 1e3:+.3f} mm subtracted from the diameter;"
        " the true bias taken as between none and twice that (fit.extra['footprint_bias_u_m'])",
    )


def cylinder_budget(
    fit: CylinderFit,
    rays: Rays | None = None,
    beams: BeamGeometry | None = None,
    *,
    errors: SensorErrors | None = None,
    noise: NoiseModel | None = None,
    calibration: CalibrationInput | None = None,
    extra_rows: Sequence[BudgetRow] = (),
    k: float = 2.0,
) -> Budget:
    """The budget of ``fit``'s diameter.

    ``rays``, ``beams``: the inliers' beams (one per inlier) of a line-of-sight fit. Without them
    (an orthogonal fit of a cloud from elsewhere) only the fit's own row, the edge row and the
    given rows are evaluated: the rig's range and angle terms need the beams. ``errors``: the
    type-B inputs (default :class:`SensorErrors`, an uncalibrated LMS1xx); ``noise``: the per-beam
    angle noise (default the seed's). ``calibration`` adds its row and drops the rows it
    ``replaces``; ``extra_rows`` are appended as they are.
    """
    err = errors if errors is not None else SensorErrors()
    nm = noise if noise is not None else NoiseModel()
    rows: list[BudgetRow] = [
        BudgetRow.of(
            "fit (type A)",
            "A",
            fit.std_diameter,
            "m",
            1.0,
            "normal",
            "the fit's covariance: range noise of the inlier beams"
            + (" (sandwich of the grazing-weighted fit)" if fit.extra.get("grazing_sigma_m", 0.0) > 0 else "")
            + (
                " (footprint fit: scaled to the cost's profile in the radius, wider than J^T J; first hit:"
                " the profile-likelihood interval's half-width / 2)"
                if fit.extra.get("footprint_profile_scale", 1.0) > 1.0
                else ""
            ),
        )
    ]
    if fit.line_of_sight and rays is not None and beams is not None:
        s = sensitivities(fit, rays, beams)
        v = beams.motor_speed_rad_s
        rows += [
            BudgetRow.of(
                "range offset",
                "B",
                err.range_offset_u_m,
                "m",
                s.range_offset,
                err.range_offset_distribution,
                "k0, a constant added to every range; LMS1xx: +-30 mm typical systematic error (SICK)",
            ),
            BudgetRow.of(
                "range scale",
                "B",
                err.range_scale_u_ppm,
                "ppm",
                s.range_scale_ppm,
                err.range_scale_distribution,
                "k1, ranges times (1 + k1); SICK publishes no scale term (in the offset's bound)",
            ),
            BudgetRow.of(
                "temperature drift",
                "B",
                err.temperature_u_k,
                "K",
                err.temperature_coeff_m_per_k * s.range_offset,
                "normal",
                f"range drift {err.temperature_coeff_m_per_k * 1e3:g} mm/K x temperature uncertainty",
            ),
            _edge_row(fit),
            _family_row(fit),
            _footprint_bias_row(fit),
            BudgetRow.of(
                "alpha zero",
                "B",
                err.alpha_zero_u_rad,
                "rad",
                s.alpha_zero,
                "normal",
                "the scanner's angular zero, common to every beam",
            ),
            BudgetRow.of(
                "alpha noise",
                "B",
                nm.sigma_alpha,
                "rad",
                s.alpha_noise,
                "normal",
                "scan-angle noise per beam (seed 003), not in the fit's range-only covariance; c: rss over beams",
            ),
            BudgetRow.of(
                "beta noise",
                "B",
                nm.sigma_beta,
                "rad",
                s.beta_noise,
                "normal",
                "motor-angle noise per beam (seed 003), not in the fit's covariance; c: rss over beams",
            ),
            BudgetRow.of(
                "beta zero",
                "B",
                err.beta_zero_u_rad,
                "rad",
                s.beta_zero,
                "normal",
                "motor zero or a constant scan-to-motor latency: a rotation about the shaft, moves the part only",
            ),
            BudgetRow.of(
                "motor timing jitter",
                "B",
                err.timing_jitter_u_s,
                "s",
                s.beta_per_scan * v,
                "normal",
                f"per scan, times the motor speed {np.rad2deg(v):g} deg/s; c: rss over scans",
            ),
            BudgetRow.of(
                "motor encoder",
                "B",
                err.encoder_u_rad,
                "rad",
                s.beta_per_scan,
                "rectangular",
                "quantisation of the motor angle, per scan; c: rss over scans",
            ),
        ]
    else:
        rows += [_edge_row(fit), _family_row(fit), _footprint_bias_row(fit)]
    if calibration is not None:
        rows = [r for r in rows if r.source not in calibration.replaces]
        rows.append(calibration.row())
    rows += list(extra_rows)
    return Budget(tuple(rows), k=k)


# --------------------------------------------------------------------------- Monte Carlo draws

#: Rows whose inputs the Monte Carlo replicas draw on the beams themselves (the others, given as a
#: diameter contribution, are drawn as a normal error of the replica's diameter). "fit (type A)" is
#: the thin-beam replicas' own spread; a footprint fit's type A beyond it (its estimated spot, the
#: radius profile) is drawn by :func:`lrms.uncertainty.monte_carlo_interval` as a normal error of
#: the diameter (:func:`lrms.uncertainty.footprint_type_a_excess`).
BEAM_SOURCES = tuple(
    s for s in SOURCES if s not in ("footprint / edge model", "edge family (model choice)", "footprint bias correction")
)


def _draw(dist: str, u: float, shape: tuple[int, ...], rng: np.random.Generator) -> FloatArray:
    if u == 0:
        return np.zeros(shape)
    if dist == "rectangular":
        half = float(np.sqrt(3.0)) * u
        return np.asarray(rng.uniform(-half, half, shape), dtype=np.float64)
    return np.asarray(rng.normal(0.0, u, shape), dtype=np.float64)


@dataclass(frozen=True)
class ReplicaSystematics:
    """The systematic effects a Monte Carlo replica (GUM Supplement 1) draws from their
    distributions, as in :func:`cylinder_budget`: ``errors`` (its type-B inputs), ``beams`` (the
    inliers' angles, scan index and motor speed) and ``diameter_u_m``, the root-sum-square of the
    rows given as a diameter contribution (edge model, calibration, extra rows), drawn as a normal
    error of each replica's diameter. Build it with :func:`replica_systematics`. (A footprint
    fit's type A beyond the thin-beam replicas' spread is not here: it is the fit's, drawn by
    :func:`lrms.uncertainty.monte_carlo_interval`.)"""

    errors: SensorErrors
    beams: BeamGeometry
    diameter_u_m: float = 0.0

    def perturb(
        self, l0: FloatArray, a0: FloatArray, b0: FloatArray, rep: int, rng: np.random.Generator
    ) -> tuple[FloatArray, FloatArray, FloatArray]:
        """Systematic errors of ``rep`` replicas of the true readings ``(l0, a0, b0)`` ``(M,)``:
        ranges ``l0 (1 + k1) + k0 + drift``, reported angles off the true beams by the zero errors
        and by a per-scan motor-angle error (timing jitter times speed, encoder quantisation).
        Returns ``(rep, M)`` arrays (the per-beam noise is added by the caller)."""
        e = self.errors
        m = l0.shape[0]
        if self.beams.alpha.shape[0] != m:
            raise LrmsError("one beam geometry per replicated beam is needed")
        k0 = _draw(e.range_offset_distribution, e.range_offset_u_m, (rep, 1), rng)
        k1 = _draw(e.range_scale_distribution, e.range_scale_u_ppm * 1e-6, (rep, 1), rng)
        drift = e.temperature_coeff_m_per_k * _draw("normal", e.temperature_u_k, (rep, 1), rng)
        l_ = l0[None, :] * (1.0 + k1) + k0 + drift
        a_ = a0[None, :] + _draw("normal", e.alpha_zero_u_rad, (rep, 1), rng)
        _, scan = np.unique(self.beams.scans(), return_inverse=True)
        n_scans = int(scan.max()) + 1 if scan.size else 0
        per_scan = _draw("normal", e.timing_jitter_u_s * self.beams.motor_speed_rad_s, (rep, n_scans), rng)
        per_scan = per_scan + _draw("rectangular", e.encoder_u_rad, (rep, n_scans), rng)
        b_ = b0[None, :] + _draw("normal", e.beta_zero_u_rad, (rep, 1), rng) + per_scan[:, scan.reshape(-1)]
        return np.asarray(l_, dtype=np.float64), np.asarray(a_, dtype=np.float64), np.asarray(b_, dtype=np.float64)


def replica_systematics(budget: Budget, errors: SensorErrors, beams: BeamGeometry) -> ReplicaSystematics:
    """The Monte Carlo counterpart of ``budget`` (built with ``errors`` and ``beams``): inputs whose
    rows the budget does not hold (superseded by a calibration) are not drawn."""
    have = {r.source for r in budget.rows}
    zero: dict[str, float] = {}
    for source, name in (
        ("range offset", "range_offset_u_m"),
        ("range scale", "range_scale_u_ppm"),
        ("temperature drift", "temperature_u_k"),
        ("alpha zero", "alpha_zero_u_rad"),
        ("beta zero", "beta_zero_u_rad"),
        ("motor timing jitter", "timing_jitter_u_s"),
        ("motor encoder", "encoder_u_rad"),
    ):
        if source not in have:
            zero[name] = 0.0
    err = errors if not zero else SensorErrors(**{**errors.__dict__, **zero})
    return ReplicaSystematics(err, beams, budget.diameter_u_beyond(BEAM_SOURCES))
