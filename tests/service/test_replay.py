"""``service.replay.max_abs_diff``: when a replayed result counts as the stored one."""

from __future__ import annotations

from service.replay import max_abs_diff

STORED = {
    "diameter_m": 0.1375,
    "uncertainty": {"k": 3.0, "d_min_m": 0.104, "gum": {"low_m": 0.137, "high_m": 0.138}},
    "sweep": {"scan_gaps": [[10, 2]], "scans_missing": 2},
    "duration_s": 10.2,
    "scanner_stats": {"lost": 2},
    "measurement_id": "abc",
}


def test_the_same_result_differs_by_nothing_and_by_the_largest_number() -> None:
    assert max_abs_diff(STORED, dict(STORED)) == 0.0
    moved = {**STORED, "diameter_m": 0.1376}
    assert abs((max_abs_diff(STORED, moved) or 0.0) - 1e-4) < 1e-12


def test_wall_time_counters_and_id_are_not_compared() -> None:
    replayed = {k: v for k, v in STORED.items() if k not in ("duration_s", "scanner_stats", "measurement_id")}
    assert max_abs_diff(STORED, {**replayed, "duration_s": 0.3}) == 0.0


def test_a_replay_that_loses_or_adds_a_field_is_not_reproduced() -> None:
    lost_top = {k: v for k, v in STORED.items() if k != "sweep"}
    assert max_abs_diff(STORED, lost_top) is None
    lost_nested = {**STORED, "uncertainty": {"k": 3.0, "d_min_m": 0.104}}
    assert max_abs_diff(STORED, lost_nested) is None
    added = {**STORED, "extra": 1.0}
    assert max_abs_diff(STORED, added) is None


def test_lists_of_other_lengths_and_values_of_other_kinds_differ() -> None:
    assert max_abs_diff(STORED, {**STORED, "sweep": {"scan_gaps": [], "scans_missing": 2}}) is None
    assert max_abs_diff({"a": True}, {"a": 1.0}) is None
    assert max_abs_diff({"a": "x"}, {"a": "y"}) is None


def test_large_numbers_are_compared_relatively_for_reproduced() -> None:
    """A calibration's condition number (2e4) differs by 4e-8 between two processes' LAPACK: 2e-12
    of it. ``max_abs_diff`` reports the absolute figure; ``relative`` scales numbers beyond 1."""
    from service.replay import REPRODUCED

    a, b = {"condition": 19351.2847078123, "k0": 0.025}, {"condition": 19351.28470777662, "k0": 0.025}
    absolute, scaled = max_abs_diff(a, b), max_abs_diff(a, b, relative=True)
    assert absolute is not None and 3.5e-8 < absolute < 3.6e-8
    assert scaled is not None and scaled <= REPRODUCED
    small = max_abs_diff({"k0": 0.025}, {"k0": 0.025 + 2e-9}, relative=True)
    assert small is not None and small > REPRODUCED
