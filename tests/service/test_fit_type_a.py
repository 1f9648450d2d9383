"""The fit's type A ``std_m`` on the sweep of ``tests/service/test_cli.py::test_measure_then_replay``,
offline: the default simulated cylinder (``seed003``, ideal sensor, sigma_l 11.67 mm), -20..70 deg
at 20 deg/s, every beam at its true motor angle (no host, no clock model, no timing error at all).

Why: that test's accuracy check (``|d - 0.1375| <= 4 std_m``) failed now and then on a loaded
machine. The timing was not it (docs/service.md, "Known limits"): replayed with the scanner clock's
offset moved 20 ms, its drift set to +-500 ppm or +-5 ms of jitter on every motor sample, a logged
failing-class sweep's diameter moved by 0.02, 0.07 and 0.09 mm. What moves is ``std_m`` itself:
40 of these offline sweeps (seeds 3-42, scan phase and noise from the seed) gave diameters
scattered by 0.445 mm, while ``std_m`` ranged from 0.107 to 0.891 mm, small exactly when the fit
came out small (correlation of error and ``std_m`` 0.65): the linearised covariance of the
grazing-weighted fit (``lrms.cylinder.bias.grazing_weighted_fit``) credits a beam that happens to
meet the fitted surface near grazing (cos(incidence) < 0.1, where that module says the linear
model fails) with most of the radius's information. Seed 13 is such a sweep (``std_m`` 0.107 mm,
error -0.24 mm): an error of the sweeps' usual size there is 4 ``std_m``.

Fixed since (``lrms.cylinder.refine.hit_information`` and ``lrms.cylinder.bias.smoothed_covariance``:
the covariance leaves out miss rows and averages the grazing sandwich over its own interval; and the
dominant-beam step keeps a clean sweep's own limb beam): the same 40 seeds give ``std_m`` 0.492 /
0.603 / 0.870 mm (min / median / max) against a 0.484 mm scatter, RMS(error / ``std_m``) 0.76, none
beyond 2 ``std_m``; seed 13 gave ``std_m`` 0.522 mm for an error of -0.60 mm. The seed-13 check
below fails on the code before those fixes.

Re-measured after the bias correction left the miss rows out of its sum (2026-11-24): ``std_m``
0.491 / 0.603 / 0.870 mm against a 0.442 mm scatter (RMS error 0.458 mm, mean +0.141 mm),
RMS(error / ``std_m``) 0.70, max |error / ``std_m``| 1.83, none beyond 2 ``std_m``; seed 13:
``std_m`` 0.522 mm for an error of -0.193 mm; seed 5: +0.348 mm, ``std_m`` 0.652 mm. Measured by
fitting seeds 3-42 with :func:`fit` (``PYTHONPATH=$PWD:tests/service python -c "import numpy as np;
from test_fit_type_a import fit; r = [fit(s) for s in range(3, 43)]; ..."``, the errors' standard
deviation, RMS and RMS(error / ``std_m``); 25 s).
"""

from __future__ import annotations

from typing import Any

import pytest

from bench.bias_miss_rows import offline_sweep as bench_offline_sweep
from lrms.cylinder import pipeline
from service import fitting
from service.config import load_config
from service.models import MeasurementRequest
from service.sweep import MappedSweep

TRUE_D = 0.1375
#: the diameters' scatter over 40 such sweeps (seeds 3-42), re-measured after the bias change (see
#: the module docstring; 0.445 mm on the code of the first measurement, 0.484 mm after the fixes)
SCATTER_M = 0.442e-3


def offline_sweep(seed: int) -> MappedSweep:
    """The default rig's constant-speed cylinder sweep (-20..70 deg), each beam at its true motor angle."""
    return bench_offline_sweep(seed, -20.0, 70.0)


def fit(seed: int) -> dict[str, float]:
    config = load_config(None)
    result = fitting.fit(offline_sweep(seed), MeasurementRequest(target="cylinder"), config)
    return {"error_m": result["diameter_m"] - TRUE_D, "std_m": result["uncertainty"]["std_m"]}


def test_a_typical_offline_sweep_is_within_its_std_m() -> None:
    """The harness itself: a sweep with an ordinary ``std_m`` measures the cylinder within it
    (seed 5: error +0.35 mm, ``std_m`` 0.65 mm)."""
    r = fit(5)
    assert 0.3e-3 <= r["std_m"] <= 1.0e-3, r
    assert abs(r["error_m"]) <= 2 * r["std_m"], r


def test_std_m_does_not_collapse_below_the_diameters_scatter(monkeypatch: pytest.MonkeyPatch) -> None:
    """Seed 13, the sweep whose ``std_m`` once collapsed to 0.107 mm: ``std_m`` within 20 % of the
    sweeps' scatter and the error within 3 ``std_m`` (a 2x under-report fails). The sweep is clean
    (no clutter beam), so the dominant-beam step (``_without_dominant_beams``) must return its fit
    unchanged: it once dropped the part's own limb beam (leverage 0.969, 1.0 mm from the true
    surface) for a cost drop of 1.5, moving the error from -0.60 to -0.76 mm (figures of the code
    before the bias change; now the error is -0.193 mm, ``std_m`` 0.522 mm)."""
    seen: list[tuple[object, object]] = []
    step = pipeline._without_dominant_beams

    def recorded(*args: Any) -> Any:
        out = step(*args)
        seen.append((args[2], out))
        return out

    monkeypatch.setattr(pipeline, "_without_dominant_beams", recorded)
    r = fit(13)
    assert seen and all(out is fit_in for fit_in, out in seen)
    assert r["std_m"] >= 0.8 * SCATTER_M, r
    assert abs(r["error_m"]) <= 3 * r["std_m"], r
