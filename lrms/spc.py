"""Statistical process control of a recipe's history: individuals / moving-range (I-MR) chart and capability.

For results ``x_1 .. x_n`` in time order (ISO 7870-2:2023; D. C. Montgomery, *Introduction to Statistical Quality
Control*, control-chart constants for subgroups of n = 2: ``d2 = 1.128``, ``D3 = 0``, ``D4 = 3.267``)::

    centre line      x̄ = mean(x)
    moving ranges    MR_i = |x_i - x_{i-1}|,  i = 2 .. n;  MR̄ = mean(MR)
    sigma (within)   σ̂ = MR̄ / d2
    I chart          UCL / LCL = x̄ ± 3 σ̂
    MR chart         UCL = D4 MR̄, LCL = D3 MR̄ = 0

Rules that flag points (these two only):

- *beyond limits* (Western Electric rule 1): a point outside the I chart's limits; a moving range above the MR
  chart's UCL (flagged at the later of its two points);
- *run of eight* (Western Electric rule 4, optional): eight successive points on the same side of the centre
  line; the eighth point and every later point of the same run are flagged. A point exactly on the centre line ends
  a run.

Capability against a tolerance ``[LSL, USL]`` (one side may be open), with the within sigma σ̂ for Cp / Cpk and
the overall sample standard deviation ``s`` (n - 1 in the denominator) for Pp / Ppk::

    Cp  = (USL - LSL) / 6 σ̂,   Cpk = min(USL - x̄, x̄ - LSL) / 3 σ̂   (one-sided: the side given; Cp undefined)
    Pp  = (USL - LSL) / 6 s,   Ppk = min(USL - x̄, x̄ - LSL) / 3 s

An index whose sigma is 0 (a constant history) is ``None`` rather than infinite.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from lrms.errors import LrmsError

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]

#: Control-chart constants for moving ranges of two points (ISO 7870-2, Montgomery Appendix VI).
D2 = 1.128
D3 = 0.0
D4 = 3.267
#: Length of the Western Electric run rule.
RUN_LENGTH = 8

RULE_BEYOND_LIMITS = "beyond 3-sigma limits (Western Electric 1)"
RULE_RUN_OF_EIGHT = "8 successive points on one side of the centre line (Western Electric 4)"


class SpcError(LrmsError):
    """Bad input to the SPC computations. ``field`` names the offending argument."""

    def __init__(self, message: str, field: str) -> None:
        super().__init__(message)
        self.field = field


@dataclass(frozen=True)
class Capability:
    """Process capability (``None`` where undefined: an open tolerance side, or a sigma of 0)."""

    lsl: float | None
    usl: float | None
    cp: float | None
    cpk: float | None
    pp: float | None
    ppk: float | None


@dataclass(frozen=True)
class IMRChart:
    """Limits of an I-MR chart from a history, the flagged points, and (with a tolerance) the capability."""

    n: int
    mean: float
    mr_bar: float
    sigma_within: float  #: MR̄ / d2
    sigma_overall: float  #: sample standard deviation (ddof = 1)
    i_ucl: float
    i_lcl: float
    mr_ucl: float
    mr_lcl: float
    moving_ranges: FloatArray  #: (n - 1,)
    beyond_limits: BoolArray  #: (n,) point outside the I chart's limits
    mr_beyond_limit: BoolArray  #: (n,) the moving range ending at this point is above the MR chart's UCL
    run_of_eight: BoolArray  #: (n,) all False when the run rule is off
    rules: tuple[str, ...]
    capability: Capability | None

    @property
    def flagged(self) -> BoolArray:
        """Points flagged by any rule applied."""
        out: BoolArray = self.beyond_limits | self.mr_beyond_limit | self.run_of_eight
        return out


def _limit(x: float | None, field: str) -> float | None:
    if x is None:
        return None
    v = float(x)
    if not math.isfinite(v):
        raise SpcError(f"{field}: must be a finite number, got {x}", field)
    return v


def runs_on_one_side(values: ArrayLike, centre: float, length: int = RUN_LENGTH) -> BoolArray:
    """Flags of points that complete (or continue) a run of ``length`` points on one side of ``centre``."""
    x = np.asarray(values, dtype=np.float64)
    side = np.sign(x - centre)
    n = side.size
    if n == 0:
        return np.zeros(0, dtype=bool)
    new_run = np.ones(n, dtype=bool)
    new_run[1:] = side[1:] != side[:-1]
    start = np.maximum.accumulate(np.where(new_run, np.arange(n), 0))
    position = np.arange(n) - start  # 0 for a run's first point
    out: BoolArray = (position >= length - 1) & (side != 0)
    return out


def capability(
    mean: float, sigma_within: float, sigma_overall: float, lsl: float | None, usl: float | None
) -> Capability:
    """Cp / Cpk (within sigma) and Pp / Ppk (overall sigma) of a process with ``mean`` against ``[lsl, usl]``."""
    lo, hi = _limit(lsl, "lsl"), _limit(usl, "usl")
    if lo is None and hi is None:
        raise SpcError("tolerance: give lsl, usl or both", "tolerance")
    if lo is not None and hi is not None and not lo < hi:
        raise SpcError(f"lsl: must be below usl ({lo} >= {hi})", "lsl")
    sides = [d for d in ((None if hi is None else hi - mean), (None if lo is None else mean - lo)) if d is not None]

    def indices(sigma: float) -> tuple[float | None, float | None]:
        if not sigma > 0:
            return None, None
        p = None if lo is None or hi is None else (hi - lo) / (6 * sigma)
        return p, min(sides) / (3 * sigma)

    cp, cpk = indices(sigma_within)
    pp, ppk = indices(sigma_overall)
    return Capability(lo, hi, cp, cpk, pp, ppk)


def imr_chart(values: ArrayLike, lsl: float | None = None, usl: float | None = None, run_rule: bool = True) -> IMRChart:
    """I-MR chart limits, flags and (if ``lsl`` and / or ``usl`` is given) capability of a history in time order."""
    x = np.asarray(values, dtype=np.float64)
    if x.ndim != 1:
        raise SpcError(f"values: need a 1-D series, got shape {x.shape}", "values")
    if x.size < 2:
        raise SpcError(f"values: need at least 2 points for a moving range, got {x.size}", "values")
    if not np.all(np.isfinite(x)):
        raise SpcError("values: all values must be finite", "values")
    mean = float(np.mean(x))
    mr = np.abs(np.diff(x))
    mr_bar = float(np.mean(mr))
    sigma_w = mr_bar / D2
    sigma_o = float(np.std(x, ddof=1))
    i_ucl, i_lcl = mean + 3 * sigma_w, mean - 3 * sigma_w
    mr_ucl, mr_lcl = D4 * mr_bar, D3 * mr_bar
    beyond = (x > i_ucl) | (x < i_lcl)
    mr_beyond = np.zeros(x.size, dtype=bool)
    mr_beyond[1:] = mr > mr_ucl
    runs = runs_on_one_side(x, mean) if run_rule else np.zeros(x.size, dtype=bool)
    rules = (RULE_BEYOND_LIMITS, RULE_RUN_OF_EIGHT) if run_rule else (RULE_BEYOND_LIMITS,)
    cap = None if lsl is None and usl is None else capability(mean, sigma_w, sigma_o, lsl, usl)
    return IMRChart(
        n=int(x.size),
        mean=mean,
        mr_bar=mr_bar,
        sigma_within=sigma_w,
        sigma_overall=sigma_o,
        i_ucl=i_ucl,
        i_lcl=i_lcl,
        mr_ucl=mr_ucl,
        mr_lcl=mr_lcl,
        moving_ranges=mr,
        beyond_limits=beyond,
        mr_beyond_limit=mr_beyond,
        run_of_eight=runs,
        rules=rules,
        capability=cap,
    )
