"""Thermal correction of hot parts to the 20 °C reference temperature (ISO 1).

A part measured at temperature ``T`` has the size ``D_T = D20 (1 + e(T))``, where ``e(T) = ΔL / L20`` is the
material's relative length change from 20 °C to ``T`` (the *thermal strain*). So::

    D20 = D_T / (1 + e(T))        (equivalently D_T / (1 + alpha_mean(20 -> T) (T - 20)))

``e(T)`` comes from a material table (:class:`Material`): piecewise polynomials in ``T`` (°C), evaluated
vectorised. The built-in tables and their sources (docs/conformity.md has the derivations):

- ``carbon_steel``: EN 1993-1-2:2005, 3.4.1.1 (structural carbon steel, 20-1200 °C). The code's curve is a
  *heating* curve that smooths the ferrite -> austenite transformation into a plateau (ΔL/L = 1.1e-2 from 750 to
  860 °C).
- ``carbon_steel_austenite``: the austenite branch of the same curve, ``2e-5 T - 6.2e-3`` (published for
  860-1200 °C), for a forging measured *on cooling* before it transforms back; 700-860 °C is our linear
  extrapolation of that branch (undercooled austenite) and carries twice the data uncertainty.
- ``c45_heating``, ``42crmo4_heating``: heating curves of two forging steels with the contraction step: ferrite
  (+ pearlite) below Ac1 on EN 1993-1-2's lower branch, austenite above Ac3 on its austenite branch, and between
  them a linear change of the transformed fraction (our model), Ac1 / Ac3 from Andrews' formulae (K. W. Andrews,
  J. Iron Steel Inst. 203 (1965) 721-727) for a stated composition (:func:`low_alloy_steel_heating`).
- ``stainless_austenitic``: EN 1993-1-2:2005, Annex C, C.3.1: ``(16 + 4.79e-3 T - 1.243e-6 T²)(T - 20) 1e-6``,
  20-1200 °C.
- ``aluminium_alloy``: EN 1999-1-2:2007, 3.3.1.1: ``0.1e-7 T² + 22.5e-6 T - 4.5e-4``, 20-500 °C.

Every table is re-referred to exactly 20 °C (``e(T) = (f(T) - f(20)) / (1 + f(20))``): EN 1999-1-2's formula
gives 4e-6 at 20 °C, which would otherwise shift a cold part by 4 µm per metre.

Uncertainty (:func:`thermal_correction`), GUM first order, as budget rows:

- the part temperature: ``u(T)`` (K) with sensitivity ``dD20/dT = -D_T e'(T) / (1 + e)²``;
- the material data: ``u(e) = u_rel |e(T)|`` with sensitivity ``dD20/de = -D_T / (1 + e)²``; ``u_rel`` is per
  table piece (5 % for the codes' curves: our estimate, the codes state none);
- inside a transformation band (where the phase fraction is unknown): ``u = |e_alpha - e_gamma| sqrt(f (1 - f) / 3)``,
  ``f = (T - T_start) / (T_end - T_start)``: mid-band that is a fraction uniform on [0, 1] (``e`` uniform between the
  ferrite and the austenite branch, ``|Δ| / sqrt(12)``), falling continuously to 0 at the band's ends (our envelope).

Any other contribution already in ``D_T`` propagates with ``dD20/dD_T = 1 / (1 + e)`` (:attr:`ThermalCorrection.scale`).
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.polynomial import Polynomial
from numpy.typing import ArrayLike, NDArray

from lrms.budget import BudgetRow
from lrms.errors import LrmsError

FloatArray = NDArray[np.float64]

#: ISO 1: the reference temperature of geometrical product specifications (°C).
REFERENCE_C = 20.0
#: Absolute zero (°C).
ABSOLUTE_ZERO_C = -273.15


class ThermalError(LrmsError):
    """Bad input to the thermal correction. ``field`` names the offending argument (for a 422 answer)."""

    def __init__(self, message: str, field: str) -> None:
        super().__init__(message)
        self.field = field


class UnknownMaterialError(ThermalError):
    """The material is not in the table."""


class TemperatureRangeError(ThermalError):
    """A temperature outside the material table's range (or not a number)."""


class AbsoluteZeroError(TemperatureRangeError):
    """A temperature below absolute zero."""


@dataclass(frozen=True)
class Piece:
    """One piece of a table: ``e = poly(T)`` for ``T`` in ``[t_lo, t_hi]`` (°C).

    ``u_rel`` is the relative standard uncertainty of ``e`` on this piece. ``band`` (for transformation ranges)
    is ``e_alpha - e_gamma`` there: the width of the uniform distribution of ``e`` when the phase fraction is unknown.
    """

    t_lo: float
    t_hi: float
    poly: Polynomial
    u_rel: float
    band: Polynomial | None = None


@dataclass(frozen=True)
class Material:
    """A table of relative length change ``e(T) = ΔL / L20`` (piecewise polynomial in °C, contiguous pieces).

    Use :meth:`from_pieces` or :meth:`from_table` to build one; both re-refer the data to exactly 20 °C.
    """

    name: str
    description: str
    source: str
    uncertainty_basis: str
    pieces: tuple[Piece, ...]

    @property
    def t_min_c(self) -> float:
        return self.pieces[0].t_lo

    @property
    def t_max_c(self) -> float:
        return self.pieces[-1].t_hi

    @property
    def breakpoints_c(self) -> FloatArray:
        """The piece limits, ``t_min .. t_max`` (°C)."""
        return np.array([p.t_lo for p in self.pieces] + [self.t_max_c])

    @classmethod
    def from_pieces(
        cls,
        name: str,
        description: str,
        source: str,
        uncertainty_basis: str,
        pieces: Sequence[Piece],
        strain_at_20: float | None = None,
    ) -> Material:
        """A table from its pieces. ``strain_at_20``: the source's ΔL/L at 20 °C, needed when the table does not
        reach down to 20 °C (the pieces are then re-referred with it)."""
        if not pieces:
            raise LrmsError(f"material {name!r}: no pieces")
        for a, b in itertools.pairwise(pieces):
            if a.t_hi != b.t_lo:
                raise LrmsError(f"material {name!r}: pieces not contiguous at {a.t_hi} / {b.t_lo} °C")
        for p in pieces:
            if not (p.t_lo < p.t_hi) or not (p.u_rel >= 0):
                raise LrmsError(f"material {name!r}: bad piece [{p.t_lo}, {p.t_hi}] u_rel={p.u_rel}")
        raw = cls(name, description, source, uncertainty_basis, tuple(pieces))
        if strain_at_20 is not None:
            f20 = float(strain_at_20)
        elif pieces[0].t_lo <= REFERENCE_C <= pieces[-1].t_hi:
            f20 = float(raw._evaluate(np.array([REFERENCE_C]), derivative=False)[0])
        else:
            raise LrmsError(f"material {name!r}: the table does not reach {REFERENCE_C} °C; give strain_at_20")
        if f20 == 0.0:
            return raw
        renorm = tuple(
            Piece(p.t_lo, p.t_hi, (p.poly - f20) / (1.0 + f20), p.u_rel, None if p.band is None else p.band / (1 + f20))
            for p in pieces
        )
        return cls(name, description, source, uncertainty_basis, renorm)

    @classmethod
    def from_table(
        cls,
        name: str,
        temperatures_c: ArrayLike,
        strain: ArrayLike,
        u_rel: float,
        source: str,
        description: str = "",
        uncertainty_basis: str = "",
    ) -> Material:
        """A table of ``(T, ΔL/L)`` points (e.g. a dilatometry run), interpolated linearly between them."""
        t = np.asarray(temperatures_c, dtype=np.float64).ravel()
        e = np.asarray(strain, dtype=np.float64).ravel()
        if t.size < 2 or t.shape != e.shape or not (np.all(np.isfinite(t)) and np.all(np.isfinite(e))):
            raise LrmsError("a material table needs >= 2 finite (temperature, strain) pairs of equal length")
        if np.any(np.diff(t) <= 0):
            raise LrmsError("a material table's temperatures must increase strictly")
        if not (math.isfinite(u_rel) and u_rel >= 0):
            raise LrmsError(f"u_rel must be >= 0, got {u_rel}")
        pieces = [
            Piece(float(t[i]), float(t[i + 1]), Polynomial.fit(t[i : i + 2], e[i : i + 2], 1).convert(), u_rel)
            for i in range(t.size - 1)
        ]
        return cls.from_pieces(name, description, source, uncertainty_basis, pieces)

    def _piece_index(self, t: FloatArray) -> NDArray[np.intp]:
        # T on a breakpoint belongs to the piece above it (the last point to the last piece)
        idx = np.searchsorted(self.breakpoints_c, t, side="right") - 1
        return np.clip(idx, 0, len(self.pieces) - 1)

    def _evaluate(self, t: FloatArray, derivative: bool) -> FloatArray:
        polys = [p.poly.deriv() if derivative else p.poly for p in self.pieces]
        vals = np.stack([poly(t) for poly in polys])  # (n_pieces, ...)
        idx = self._piece_index(t)
        out: FloatArray = np.take_along_axis(vals, idx[np.newaxis], axis=0)[0]
        return out

    def check_temperature(self, temperature_c: ArrayLike, field: str = "temperature_c") -> FloatArray:
        """Float array of the temperatures, or :class:`TemperatureRangeError` if any is outside the table."""
        t = np.asarray(temperature_c, dtype=np.float64)
        if not np.all(np.isfinite(t)):
            raise TemperatureRangeError(f"{field}: temperature must be a finite number", field)
        if np.any(t < ABSOLUTE_ZERO_C):
            raise AbsoluteZeroError(
                f"{field}: {float(np.min(t))} °C is below absolute zero ({ABSOLUTE_ZERO_C} °C)", field
            )
        if np.any(t < self.t_min_c) or np.any(t > self.t_max_c):
            bad = float(t[(t < self.t_min_c) | (t > self.t_max_c)].ravel()[0])
            raise TemperatureRangeError(
                f"{field}: {bad} °C is outside the range of material {self.name!r} "
                f"({self.t_min_c:g} .. {self.t_max_c:g} °C)",
                field,
            )
        return t

    def strain(self, temperature_c: ArrayLike) -> FloatArray:
        """``e(T) = ΔL / L20``, dimensionless, same shape as the input."""
        return self._evaluate(self.check_temperature(temperature_c), derivative=False)

    def strain_derivative(self, temperature_c: ArrayLike) -> FloatArray:
        """``de/dT`` (1/K): the instantaneous expansion coefficient relative to the 20 °C length."""
        return self._evaluate(self.check_temperature(temperature_c), derivative=True)

    def mean_coefficient(self, temperature_c: ArrayLike) -> FloatArray:
        """``alpha_mean(20 -> T) = e(T) / (T - 20)`` (1/K); at exactly 20 °C the instantaneous coefficient."""
        t = self.check_temperature(temperature_c)
        e = self._evaluate(t, derivative=False)
        d = self._evaluate(t, derivative=True)
        dt = t - REFERENCE_C
        at_ref = dt == 0
        return np.where(at_ref, d, e / np.where(at_ref, 1.0, dt))

    def strain_uncertainties(self, temperature_c: ArrayLike) -> tuple[FloatArray, FloatArray]:
        """``(u_data, u_phase)``: standard uncertainties of ``e`` from the data and from an unknown phase fraction.

        ``u_phase = |e_alpha - e_gamma| sqrt(f (1 - f) / 3)`` with ``f`` the position in the transformation piece:
        ``|Δ| / sqrt(12)`` (a fraction uniform on [0, 1]) mid-band, falling to 0 at the band's ends.
        """
        t = self.check_temperature(temperature_c)
        idx = self._piece_index(t)
        e = self._evaluate(t, derivative=False)
        u_rel = np.array([p.u_rel for p in self.pieces])[idx]
        bands = np.stack([np.zeros_like(t) if p.band is None else p.band(t) for p in self.pieces])
        band = np.take_along_axis(bands, idx[np.newaxis], axis=0)[0]
        lo = np.array([p.t_lo for p in self.pieces])[idx]
        hi = np.array([p.t_hi for p in self.pieces])[idx]
        f = np.clip((t - lo) / (hi - lo), 0.0, 1.0)
        return u_rel * np.abs(e), np.abs(band) * np.sqrt(f * (1.0 - f) / 3.0)


# ----------------------------------------------------------------------------------------------- the tables

#: EN 1993-1-2:2005, 3.4.1.1, carbon steel: ΔL/L for 20 <= T < 750 °C.
EN1993_FERRITE = Polynomial([-2.416e-4, 1.2e-5, 0.4e-8])
#: ... the plateau for 750 <= T <= 860 °C.
EN1993_PLATEAU = Polynomial([1.1e-2])
#: ... austenite, 860 < T <= 1200 °C.
EN1993_AUSTENITE = Polynomial([-6.2e-3, 2e-5])
#: EN 1993-1-2:2005, Annex C, C.3.1, stainless steels: (16 + 4.79e-3 T - 1.243e-6 T^2) (T - 20) 1e-6.
EN1993_STAINLESS = Polynomial([16.0, 4.79e-3, -1.243e-6]) * Polynomial([-20.0, 1.0]) * 1e-6
#: EN 1999-1-2:2007, 3.3.1.1, aluminium alloys: 0.1e-7 T^2 + 22.5e-6 T - 4.5e-4, 20 <= T <= 500 °C.
EN1999_ALUMINIUM = Polynomial([-4.5e-4, 22.5e-6, 0.1e-7])

#: Relative standard uncertainty given to the codes' curves (our estimate; the codes state none).
U_REL_CODE = 0.05
_U_BASIS = (
    "5 % of ΔL/L (standard): our estimate for a design-code curve applied to one grade; the code states no "
    "uncertainty. Replace by the grade's dilatometry where it matters."
)
_U_BASIS_STEEL = (
    _U_BASIS + " Inside the transformation range the unknown ferrite/austenite fraction adds "
    "u = |e_alpha - e_gamma| sqrt(f (1 - f) / 3), f the position in the range (|Δ| / sqrt(12) mid-range)."
)


def andrews_ac1_ac3(
    c: float, mn: float = 0.0, si: float = 0.0, ni: float = 0.0, cr: float = 0.0, mo: float = 0.0,
    v: float = 0.0, w: float = 0.0, as_: float = 0.0,
) -> tuple[float, float]:  # fmt: skip
    """Ac1 and Ac3 (°C) from the composition in mass %, K. W. Andrews, JISI 203 (1965) 721-727::

    Ac1 = 723 - 10.7 Mn - 16.9 Ni + 29.1 Si + 16.9 Cr + 290 As + 6.38 W
    Ac3 = 910 - 203 sqrt(C) - 15.2 Ni + 44.7 Si + 104 V + 31.5 Mo + 13.1 W

    Valid for low-alloy hypo-eutectoid steels (C <= 0.6 %); slow heating (equilibrium-like).
    """
    comp = {"c": c, "mn": mn, "si": si, "ni": ni, "cr": cr, "mo": mo, "v": v, "w": w, "as_": as_}
    for key, val in comp.items():
        if not (math.isfinite(val) and val >= 0):
            raise ThermalError(f"{key}: mass fraction must be >= 0 %, got {val}", key)
    if not (0 < c <= 0.6):
        raise ThermalError(f"c: Andrews' Ac3 formula covers 0 < C <= 0.6 %, got {c}", "c")
    ac1 = 723 - 10.7 * mn - 16.9 * ni + 29.1 * si + 16.9 * cr + 290 * as_ + 6.38 * w
    ac3 = 910 - 203 * math.sqrt(c) - 15.2 * ni + 44.7 * si + 104 * v + 31.5 * mo + 13.1 * w
    return ac1, ac3


def low_alloy_steel_heating(name: str, composition: Mapping[str, float], t_max_c: float = 1200.0) -> Material:
    """A heating curve with the contraction at the ferrite -> austenite transformation.

    Below Ac1: EN 1993-1-2's lower branch (ferrite + pearlite). Above Ac3: its austenite branch ``2e-5 T - 6.2e-3``
    (extended below 860 °C when Ac3 is lower). Between Ac1 and Ac3 the austenite fraction grows linearly with T (our
    simplification of the kinetics), so ``e = (1 - f) e_alpha + f e_gamma``: the length drops by
    ``e_alpha(Ac1) - e_gamma(Ac3)`` minus the austenite's own growth. Ac1 / Ac3 from :func:`andrews_ac1_ac3`.
    """
    ac1, ac3 = andrews_ac1_ac3(**composition)
    if not (REFERENCE_C < ac1 < ac3 < t_max_c <= 1200.0):
        raise ThermalError(f"{name}: Ac1 {ac1:.1f} / Ac3 {ac3:.1f} °C do not fit in 20 .. {t_max_c} °C", "composition")
    frac = Polynomial([-ac1, 1.0]) / (ac3 - ac1)
    mix = (1 - frac) * EN1993_FERRITE + frac * EN1993_AUSTENITE
    comp = ", ".join(f"{k.rstrip('_').capitalize()} {v:g}" for k, v in composition.items())
    return Material.from_pieces(
        name,
        f"low-alloy steel ({comp} mass %), heating; Ac1 {ac1:.0f} °C, Ac3 {ac3:.0f} °C",
        "EN 1993-1-2:2005 3.4.1.1 branches (ferrite below Ac1, austenite above Ac3); Ac1/Ac3: Andrews, "
        "JISI 203 (1965) 721-727; linear transformed fraction between them (lrms model)",
        _U_BASIS_STEEL,
        [
            Piece(REFERENCE_C, ac1, EN1993_FERRITE, U_REL_CODE),
            Piece(ac1, ac3, mix, U_REL_CODE, band=EN1993_FERRITE - EN1993_AUSTENITE),
            Piece(ac3, t_max_c, EN1993_AUSTENITE, U_REL_CODE),
        ],
    )


def _builtin() -> dict[str, Material]:
    mats = [
        Material.from_pieces(
            "carbon_steel",
            "structural carbon steel, heating curve (transformation smoothed into a plateau)",
            "EN 1993-1-2:2005, 3.4.1.1, Eq. 3.1a-c",
            _U_BASIS_STEEL,
            [
                Piece(20.0, 750.0, EN1993_FERRITE, U_REL_CODE),
                Piece(750.0, 860.0, EN1993_PLATEAU, U_REL_CODE, band=EN1993_FERRITE - EN1993_AUSTENITE),
                Piece(860.0, 1200.0, EN1993_AUSTENITE, U_REL_CODE),
            ],
        ),
        Material.from_pieces(
            "carbon_steel_austenite",
            "carbon / low-alloy steel, fully austenitic (a forging measured while cooling, before it transforms)",
            "EN 1993-1-2:2005, 3.4.1.1, Eq. 3.1c (860-1200 °C); 700-860 °C: linear extrapolation (lrms)",
            _U_BASIS + " Doubled (10 %) on the extrapolated 700-860 °C piece.",
            [
                Piece(700.0, 860.0, EN1993_AUSTENITE, 2 * U_REL_CODE),
                Piece(860.0, 1200.0, EN1993_AUSTENITE, U_REL_CODE),
            ],
            strain_at_20=float(EN1993_FERRITE(REFERENCE_C)),
        ),
        low_alloy_steel_heating("c45_heating", {"c": 0.45, "mn": 0.65, "si": 0.25}),
        low_alloy_steel_heating("42crmo4_heating", {"c": 0.42, "mn": 0.75, "si": 0.25, "cr": 1.05, "mo": 0.22}),
        Material.from_pieces(
            "stainless_austenitic",
            "austenitic stainless steel (1.4301 / 304 type)",
            "EN 1993-1-2:2005, Annex C, C.3.1",
            _U_BASIS,
            [Piece(20.0, 1200.0, EN1993_STAINLESS, U_REL_CODE)],
        ),
        Material.from_pieces(
            "aluminium_alloy",
            "aluminium alloys",
            "EN 1999-1-2:2007, 3.3.1.1, Eq. 3.1 (re-referred to 0 at 20 °C)",
            _U_BASIS,
            [Piece(20.0, 500.0, EN1999_ALUMINIUM, U_REL_CODE)],
        ),
    ]
    return {m.name: m for m in mats}


#: The built-in material tables by name.
MATERIALS: Mapping[str, Material] = _builtin()


def material(name: str | Material) -> Material:
    """The material table called ``name`` (a :class:`Material` passes through)."""
    if isinstance(name, Material):
        return name
    try:
        return MATERIALS[name]
    except (KeyError, TypeError):
        raise UnknownMaterialError(
            f"material: unknown material {name!r}; known: {', '.join(sorted(MATERIALS))}", "material"
        ) from None


# ------------------------------------------------------------------------------------------- the correction


def correct_to_20c(d_measured: ArrayLike, temperature_c: ArrayLike, mat: str | Material) -> FloatArray:
    """``D20 = D_T / (1 + e(T))``, vectorised (inputs broadcast). Any length unit; the result has the same."""
    m = material(mat)
    d = np.asarray(d_measured, dtype=np.float64)
    if not np.all(np.isfinite(d)):
        raise ThermalError("d_measured: must be finite", "d_measured")
    return d / (1.0 + m.strain(temperature_c))


@dataclass(frozen=True)
class ThermalCorrection:
    """A diameter measured hot, corrected to 20 °C, with the thermal rows of its uncertainty budget."""

    material: str
    temperature_c: float
    u_temperature_k: float
    d_measured_m: float
    d20_m: float
    strain: float  #: e(T) = ΔL/L20
    strain_derivative_per_k: float  #: de/dT
    mean_coefficient_per_k: float  #: alpha_mean(20 -> T)
    scale: float  #: dD20/dD_T = 1 / (1 + e): multiply D_T's other uncertainty rows by it
    rows: tuple[BudgetRow, ...]

    @property
    def u_thermal_m(self) -> float:
        """The root sum of squares of the thermal rows (m)."""
        return math.sqrt(sum(r.u_m**2 for r in self.rows))


def thermal_correction(
    d_measured_m: float, temperature_c: float, u_temperature_k: float, mat: str | Material
) -> ThermalCorrection:
    """Correct one diameter to 20 °C and give its temperature and material-data budget rows."""
    m = material(mat)
    d = float(d_measured_m)
    if not (math.isfinite(d) and d > 0):
        raise ThermalError(f"d_measured_m: must be a finite length > 0, got {d_measured_m}", "d_measured_m")
    u_t = float(u_temperature_k)
    if not (math.isfinite(u_t) and u_t >= 0):
        raise ThermalError(
            f"u_temperature_k: standard uncertainty must be finite and >= 0, got {u_temperature_k}",
            "u_temperature_k",
        )
    t = float(m.check_temperature(float(temperature_c), field="temperature_c"))
    ta = np.array([t])
    e = float(m.strain(ta)[0])
    de = float(m.strain_derivative(ta)[0])
    u_data, u_phase = (float(a[0]) for a in m.strain_uncertainties(ta))
    scale = 1.0 / (1.0 + e)
    c_e = -d * scale**2  # dD20/de
    c_t = c_e * de  # dD20/dT
    note_t = f"de/dT = {de:.4g} /K"
    kinks = m.breakpoints_c[1:-1]
    if np.any(np.abs(kinks - t) <= 2 * u_t):
        note_t += "; a kink of the table lies within T ± 2u(T): the first-order sensitivity is only local"
    rows = [
        BudgetRow("part temperature", "B", u_t, "K", c_t, abs(c_t) * u_t, "normal", note_t),
        BudgetRow(
            f"thermal expansion data ({m.name})",
            "B",
            u_data,
            "1",
            c_e,
            abs(c_e) * u_data,
            "normal",
            f"u_rel of ΔL/L; {m.source}",
        ),
    ]
    if u_phase > 0:
        rows.append(
            BudgetRow(
                "ferrite/austenite fraction",
                "B",
                u_phase,
                "1",
                c_e,
                abs(c_e) * u_phase,
                "rectangular",
                "T inside the transformation range: the ferrite/austenite fraction is unknown",
            )
        )
    return ThermalCorrection(
        material=m.name,
        temperature_c=t,
        u_temperature_k=u_t,
        d_measured_m=d,
        d20_m=d * scale,
        strain=e,
        strain_derivative_per_k=de,
        mean_coefficient_per_k=float(m.mean_coefficient(ta)[0]),
        scale=scale,
        rows=tuple(rows),
    )
