"""Thermal correction to 20 °C: the material tables against hand-computed values, the budget rows, bad input."""

from __future__ import annotations

import math

import numpy as np
import pytest

from lrms.errors import LrmsError
from lrms.thermal import (
    MATERIALS,
    AbsoluteZeroError,
    Material,
    TemperatureRangeError,
    ThermalError,
    UnknownMaterialError,
    andrews_ac1_ac3,
    correct_to_20c,
    material,
    thermal_correction,
)


def test_every_table_is_zero_at_the_reference_temperature() -> None:
    for name, mat in MATERIALS.items():
        if mat.t_min_c <= 20.0:
            assert abs(float(mat.strain(20.0))) < 1e-15, name


@pytest.mark.parametrize(
    ("name", "t", "expected"),
    [
        # EN 1993-1-2 3.4.1.1: 1.2e-5*500 + 0.4e-8*500^2 - 2.416e-4 = 6e-3 + 1e-3 - 0.2416e-3
        ("carbon_steel", 500.0, 6.7584e-3),
        ("carbon_steel", 800.0, 1.1e-2),  # the plateau
        ("carbon_steel", 1000.0, 1.38e-2),  # 2e-5*1000 - 6.2e-3
        ("carbon_steel_austenite", 800.0, 9.8e-3),  # 2e-5*800 - 6.2e-3 (extrapolated branch)
        # EN 1993-1-2 Annex C: (16 + 4.79 - 1.243) * 980 * 1e-6
        ("stainless_austenitic", 1000.0, 19.547 * 980e-6),
        # EN 1999-1-2: f(500) = 2.5e-3 + 11.25e-3 - 0.45e-3 = 13.3e-3, f(20) = 4e-6 -> (13.3e-3 - 4e-6) / 1.000004
        ("aluminium_alloy", 500.0, 0.013296 / 1.000004),
        ("c45_heating", 900.0, 1.18e-2),  # austenite above Ac3
        ("c45_heating", 600.0, 1.2e-5 * 600 + 0.4e-8 * 360000 - 2.416e-4),  # ferrite below Ac1
    ],
)
def test_strain_against_hand_values(name: str, t: float, expected: float) -> None:
    assert float(material(name).strain(t)) == pytest.approx(expected, rel=1e-12, abs=1e-15)


def test_correction_hand_values_and_vectorised() -> None:
    d = correct_to_20c([0.5, 0.5, 0.32], [500.0, 800.0, 1000.0], "carbon_steel")
    np.testing.assert_allclose(d, [0.5 / 1.0067584, 0.5 / 1.011, 0.32 / 1.0138], rtol=1e-13)
    # broadcasting: one diameter at many temperatures
    grid = np.linspace(20.0, 1200.0, 1180).reshape(59, 20)
    out = correct_to_20c(1.0, grid, "stainless_austenitic")
    assert out.shape == grid.shape
    assert out[0, 0] == 1.0 and np.all(np.diff(out.ravel()) < 0)  # stainless has no transformation


def test_andrews_transformation_temperatures_c45() -> None:
    ac1, ac3 = andrews_ac1_ac3(c=0.45, mn=0.65, si=0.25)
    assert ac1 == pytest.approx(723 - 6.955 + 7.275)  # 723.32
    assert ac3 == pytest.approx(910 - 203 * 0.6708204 + 11.175, abs=1e-5)  # 784.9985


def test_c45_contracts_between_ac1_and_ac3() -> None:
    mat = material("c45_heating")
    ac1, ac3 = 723.32, 910 - 203 * math.sqrt(0.45) + 11.175  # Andrews, as above
    t = np.linspace(ac1 + 0.01, ac3 - 0.01, 50)
    e = mat.strain(t)
    assert np.all(np.diff(e) < 0) and np.all(mat.strain_derivative(t) < 0)
    # the length drops from ~10.53e-3 at Ac1 to 9.5e-3 at Ac3 (-0.1 %)
    e_ac1 = 1.2e-5 * ac1 + 0.4e-8 * ac1**2 - 2.416e-4
    assert float(mat.strain(ac1)) == pytest.approx(e_ac1, rel=1e-9)
    assert e_ac1 == pytest.approx(10.531e-3, abs=1e-6)
    assert float(mat.strain(ac3)) == pytest.approx(2e-5 * ac3 - 6.2e-3, rel=1e-9)
    # mid-range: the mean of the two branches
    tm = 0.5 * (ac1 + ac3)
    mid = 0.5 * ((1.2e-5 * tm + 0.4e-8 * tm**2 - 2.416e-4) + (2e-5 * tm - 6.2e-3))
    assert float(mat.strain(tm)) == pytest.approx(mid, rel=1e-9)


def test_tables_are_continuous_at_their_breakpoints() -> None:
    for name, mat in MATERIALS.items():
        for b in mat.breakpoints_c[1:-1]:
            below, above = mat.strain([b - 1e-9, b + 1e-9])
            # EN 1993-1-2's own curve jumps by 8.4e-6 at 750 °C (11.0084e-3 vs the 1.1e-2 plateau)
            assert abs(below - above) < 1e-5, (name, b)


def test_mean_coefficient() -> None:
    mat = material("carbon_steel")
    np.testing.assert_allclose(mat.mean_coefficient([20.0, 1000.0]), [1.2e-5 + 2 * 0.4e-8 * 20, 1.38e-2 / 980])


def test_budget_rows_hand_values() -> None:
    r = thermal_correction(1.0, 1000.0, 10.0, "carbon_steel")
    c_e = -1.0 / 1.0138**2
    assert r.d20_m == pytest.approx(1.0 / 1.0138, rel=1e-14)
    assert r.scale == pytest.approx(1.0 / 1.0138, rel=1e-14)
    temp, data = r.rows
    assert (temp.source, temp.unit, temp.u_x) == ("part temperature", "K", 10.0)
    assert temp.c == pytest.approx(c_e * 2e-5, rel=1e-12)
    assert temp.u_m == pytest.approx(1.945922e-4, rel=1e-6)  # 10 K * 2e-5 / 1.0138^2
    assert (data.unit, data.u_x) == ("1", pytest.approx(0.05 * 0.0138))
    assert data.c == pytest.approx(c_e, rel=1e-12)
    assert data.u_m == pytest.approx(6.713431e-4, rel=1e-6)  # 6.9e-4 / 1.0138^2
    assert r.u_thermal_m == pytest.approx(math.hypot(temp.u_m, data.u_m))
    for row in r.rows:
        assert row.type == "B" and row.u_m == pytest.approx(abs(row.c) * row.u_x)


def test_phase_fraction_row_inside_the_transformation_range() -> None:
    r = thermal_correction(1.0, 805.0, 10.0, "carbon_steel")  # middle of 750-860: f = 0.5
    assert [row.source for row in r.rows][-1] == "ferrite/austenite fraction"
    delta = (1.2e-5 * 805 + 0.4e-8 * 805**2 - 2.416e-4) - (2e-5 * 805 - 6.2e-3)  # 2.1105e-3
    assert r.rows[-1].u_x == pytest.approx(delta / math.sqrt(12), rel=1e-12)
    assert r.rows[0].u_m == 0.0  # flat plateau: the temperature does not matter there ...
    assert "kink" not in r.rows[0].note
    near = thermal_correction(1.0, 745.0, 10.0, "carbon_steel")  # ... but near its start the slope changes
    assert "kink" in near.rows[0].note
    # outside a band there is no phase row, and the phase row vanishes at the band's ends
    assert len(thermal_correction(1.0, 1000.0, 10.0, "carbon_steel").rows) == 2
    _, u_phase = material("c45_heating").strain_uncertainties([723.33, 754.16, 784.99])
    assert u_phase[0] < 0.05 * u_phase[1] and u_phase[2] < 0.05 * u_phase[1]


def test_material_from_a_dilatometry_table() -> None:
    mat = Material.from_table("test", [20.0, 120.0, 220.0], [0.0, 1.2e-3, 2.6e-3], 0.02, "test data")
    assert float(mat.strain(170.0)) == pytest.approx(1.9e-3)
    assert float(mat.strain_derivative(170.0)) == pytest.approx(14e-6)
    assert thermal_correction(0.1, 170.0, 0.0, mat).d20_m == pytest.approx(0.1 / 1.0019)
    with pytest.raises(LrmsError, match="increase"):
        Material.from_table("bad", [20.0, 20.0], [0.0, 0.0], 0.02, "x")


@pytest.mark.parametrize(
    ("kwargs", "error", "field", "match"),
    [
        ({"temperature_c": -300.0}, AbsoluteZeroError, "temperature_c", "absolute zero"),
        ({"temperature_c": 1300.0}, TemperatureRangeError, "temperature_c", r"20 \.\. 1200"),
        ({"temperature_c": 10.0}, TemperatureRangeError, "temperature_c", "outside"),
        ({"temperature_c": math.nan}, TemperatureRangeError, "temperature_c", "finite"),
        ({"u_temperature_k": -1.0}, ThermalError, "u_temperature_k", ">= 0"),
        ({"mat": "unobtainium"}, UnknownMaterialError, "material", "carbon_steel"),
        ({"d_measured_m": 0.0}, ThermalError, "d_measured_m", "> 0"),
    ],
)
def test_bad_input_is_refused_with_the_field_named(
    kwargs: dict[str, object], error: type[Exception], field: str, match: str
) -> None:
    args: dict[str, object] = {
        "d_measured_m": 1.0,
        "temperature_c": 900.0,
        "u_temperature_k": 5.0,
        "mat": "carbon_steel",
    }
    args.update(kwargs)
    with pytest.raises(error, match=match) as info:
        thermal_correction(**args)  # type: ignore[arg-type]
    assert isinstance(info.value, LrmsError) and info.value.field == field  # type: ignore[attr-defined]


def test_range_limits_per_material() -> None:
    with pytest.raises(TemperatureRangeError, match="aluminium_alloy"):
        correct_to_20c(1.0, [100.0, 550.0], "aluminium_alloy")
    with pytest.raises(TemperatureRangeError):
        material("carbon_steel_austenite").strain(650.0)  # austenite is not offered below 700 °C
    with pytest.raises(ThermalError, match=r"C <= 0\.6"):
        andrews_ac1_ac3(c=0.9)
