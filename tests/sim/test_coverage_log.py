"""The coverage run's per-sweep records (bench/coverage_log.py): resuming and pooling count each sweep once."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import pytest
from scipy.stats import binomtest

from bench.coverage_log import append_record, coverage_interval, done_sweeps, read_records, summarize


def rec(sweep: int, status: str = "ok", error: float = 0.001, u: float = 0.002, seed: int = 11) -> dict[str, Any]:
    r: dict[str, Any] = {
        "scene": "seed003-room",
        "cloud": "roi",
        "fit": "footprint",
        "case": "LMS1xx thr 30 % 1st",
        "sub_rays": 128,
        "hold_spot": False,
        "seed": seed,
        "sweep": sweep,
        "status": status,
        "cpu_s": 10.0,
    }
    if status == "ok":
        r.update(error_m=error, u_m=u, U_m=2 * u, covered=abs(error) <= 2 * u, won="first", tau=math.nan)
    return r


def test_records_round_trip_and_a_torn_last_line_is_skipped(tmp_path: Path) -> None:
    path = tmp_path / "run.jsonl"
    append_record(path, rec(0))
    append_record(path, rec(1, status="failed"))
    with path.open("a") as f:
        f.write('{"scene": "seed003-ro')  # a run killed while writing
    back = read_records([path, tmp_path / "missing.jsonl"])
    assert [r["sweep"] for r in back] == [0, 1]
    assert back[0]["tau"] is None  # NaN written as null: the file stays strict JSON
    assert len(done_sweeps(path)) == 2 and done_sweeps(None) == set()


def test_pooling_counts_each_sweep_once_per_case_and_seed() -> None:
    records = [rec(0, error=0.001), rec(1, error=0.005), rec(2, status="failed"), rec(3, status="gross")]
    records += [rec(0, error=0.009)]  # the same sweep again (overlapping chunks): the first record counts
    records += [rec(0, error=0.001, seed=12)]  # another seed's sweep 0: a different sweep
    records += [{**rec(0), "case": "LMS1xx thr 30 % wtd"}]  # another member
    by_case = {s.key[3]: s for s in summarize(records)}
    first = by_case["LMS1xx thr 30 % 1st"]
    assert (first.n, first.covered, first.failed, first.gross, first.duplicates) == (3, 2, 1, 1, 1)
    assert first.seeds == {11, 12} and first.errors == [0.001, 0.005, 0.001]
    assert by_case["LMS1xx thr 30 % wtd"].n == 1


def test_runs_of_several_sub_ray_patterns_pool_apart_from_one_pattern_runs() -> None:
    """``patterns`` names the case (bench_sensor_model --patterns); a record without the field, from
    before it, had one pattern and pools with ``patterns: 1``."""
    records = [rec(0), {**rec(1), "patterns": 1}, {**rec(0), "patterns": 4}, {**rec(1), "patterns": 4}]
    by_patterns = {s.key[-1]: s for s in summarize(records)}
    assert set(by_patterns) == {1, 4}
    assert by_patterns[1].n == 2 and by_patterns[4].n == 2


@pytest.mark.parametrize(("k", "n"), [(0, 20), (37, 40), (380, 400), (400, 400)])
def test_coverage_interval_is_the_exact_binomial_one(k: int, n: int) -> None:
    ci = binomtest(k, n).proportion_ci(0.95, method="exact")
    assert coverage_interval(k, n) == pytest.approx((ci.low, ci.high), abs=1e-9)


def test_coverage_interval_rejects_an_impossible_count() -> None:
    with pytest.raises(ValueError, match="0 <= k <= n"):
        coverage_interval(5, 4)
