"""I-MR chart limits, flags and Cp / Cpk / Pp / Ppk against hand-computed numbers."""

from __future__ import annotations

import math

import numpy as np
import pytest

from lrms.errors import LrmsError
from lrms.spc import RULE_RUN_OF_EIGHT, SpcError, capability, imr_chart, runs_on_one_side


def test_limits_and_capability_of_a_small_series() -> None:
    # x = 5 7 6 9 8: mean 7; MR = 2 1 3 1, MR-bar 1.75; sigma_w = 1.75 / 1.128 = 1.5514184
    # deviations -2 0 -1 2 1: sum of squares 10, s = sqrt(10 / 4) = 1.5811388
    c = imr_chart([5.0, 7.0, 6.0, 9.0, 8.0], lsl=2.0, usl=14.0)
    assert c.n == 5 and c.mean == 7.0 and c.mr_bar == 1.75
    np.testing.assert_array_equal(c.moving_ranges, [2.0, 1.0, 3.0, 1.0])
    assert c.sigma_within == pytest.approx(1.5514184, abs=1e-7)
    assert c.sigma_overall == pytest.approx(1.5811388, abs=1e-7)
    assert c.i_ucl == pytest.approx(11.6542553, abs=1e-7)  # 7 + 3 * 1.5514184
    assert c.i_lcl == pytest.approx(2.3457447, abs=1e-7)
    assert c.mr_ucl == pytest.approx(5.71725)  # 3.267 * 1.75
    assert c.mr_lcl == 0.0
    assert not c.flagged.any()
    cap = c.capability
    assert cap is not None
    assert cap.cp == pytest.approx(1.289143, abs=1e-6)  # 12 / (6 * 1.5514184)
    assert cap.cpk == pytest.approx(1.074286, abs=1e-6)  # min(14 - 7, 7 - 2) / (3 * 1.5514184) = 5 / 4.6542553
    assert cap.pp == pytest.approx(1.264911, abs=1e-6)  # 12 / (6 * 1.5811388)
    assert cap.ppk == pytest.approx(1.054093, abs=1e-6)  # 5 / (3 * 1.5811388)


def test_one_sided_capability() -> None:
    c = imr_chart([5.0, 7.0, 6.0, 9.0, 8.0], usl=10.0)
    assert c.capability is not None
    assert c.capability.cp is None and c.capability.pp is None
    assert c.capability.cpk == pytest.approx(3.0 / (3 * 1.75 / 1.128))  # (USL - mean) / 3 sigma
    low = imr_chart([5.0, 7.0, 6.0, 9.0, 8.0], lsl=6.0).capability
    assert low is not None and low.ppk == pytest.approx(1.0 / (3 * math.sqrt(2.5)))
    # a mean outside the tolerance gives a negative Cpk
    out = capability(7.0, 1.0, 1.0, lsl=8.0, usl=20.0)
    assert out.cpk == pytest.approx(-1.0 / 3.0)
    assert imr_chart([1.0, 2.0]).capability is None  # no tolerance, no capability


def test_point_and_moving_ranges_beyond_limits() -> None:
    x = [10.0, 10.2, 9.9, 10.1, 10.0, 30.0, 10.0, 9.8]
    # mean 100 / 8 = 12.5; MR = .2 .3 .2 .1 20 20 .2, MR-bar = 41 / 7 = 5.857143; sigma_w = 5.192503
    c = imr_chart(x)
    assert c.mean == pytest.approx(12.5) and c.mr_bar == pytest.approx(41.0 / 7.0)
    assert c.i_ucl == pytest.approx(12.5 + 3 * 41.0 / 7.0 / 1.128)  # 28.0775: 30 is beyond
    np.testing.assert_array_equal(np.flatnonzero(c.beyond_limits), [5])
    # MR UCL = 3.267 * 5.857143 = 19.135: both 20's, flagged at the later point of each pair
    np.testing.assert_array_equal(np.flatnonzero(c.mr_beyond_limit), [5, 6])
    np.testing.assert_array_equal(np.flatnonzero(c.flagged), [5, 6])


def test_run_of_eight_on_one_side() -> None:
    x = [-1.0] * 4 + [1.0, 1.5] * 4 + [1.0] + [-1.0] * 3  # nine points above the centre line, indices 4 .. 12
    c = imr_chart(x)
    assert c.mean == pytest.approx((-4 + 10 + 1 - 3) / 16)  # 0.25: the nine stay above it
    assert RULE_RUN_OF_EIGHT in c.rules
    np.testing.assert_array_equal(np.flatnonzero(c.run_of_eight), [11, 12])  # the 8th and the 9th
    off = imr_chart(x, run_rule=False)
    assert not off.run_of_eight.any() and off.rules == (off.rules[0],)
    # a point exactly on the centre line ends the run
    flags = runs_on_one_side([1.0] * 7 + [0.0] + [1.0] * 7, centre=0.0)
    assert not flags.any()
    np.testing.assert_array_equal(np.flatnonzero(runs_on_one_side([-2.0] * 10, 0.0)), [7, 8, 9])


def test_constant_history_has_no_capability_index() -> None:
    c = imr_chart([3.0, 3.0, 3.0], lsl=2.0, usl=4.0)
    assert c.sigma_within == 0.0 and c.i_ucl == c.i_lcl == 3.0
    assert c.capability is not None and c.capability.cp is None and c.capability.ppk is None
    assert not c.beyond_limits.any()


@pytest.mark.parametrize(
    ("values", "kwargs", "field", "match"),
    [
        ([1.0], {}, "values", "at least 2"),
        ([], {}, "values", "at least 2"),
        ([1.0, math.nan, 2.0], {}, "values", "finite"),
        ([[1.0, 2.0], [3.0, 4.0]], {}, "values", "1-D"),
        ([1.0, 2.0, 3.0], {"lsl": 5.0, "usl": 5.0}, "lsl", "below usl"),
        ([1.0, 2.0, 3.0], {"lsl": 6.0, "usl": 5.0}, "lsl", "below usl"),
        ([1.0, 2.0, 3.0], {"usl": math.inf}, "usl", "finite"),
    ],
)
def test_bad_input(values: list[float], kwargs: dict[str, float], field: str, match: str) -> None:
    with pytest.raises(SpcError, match=match) as info:
        imr_chart(values, **kwargs)
    assert info.value.field == field and isinstance(info.value, LrmsError)
