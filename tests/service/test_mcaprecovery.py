"""A raw log cut short, rebuilt into a complete indexed file (``service.mcaprecovery``)."""

from __future__ import annotations

from pathlib import Path

import pytest
from mcap.reader import make_reader

from service import mcaplog as ml
from service import mcaprecovery as mr
from tests.service.test_mcaplog import T0, _write


def _indexed(path: Path) -> list[tuple[str, int, bytes]]:
    """Every message through the indexed reader (it needs the summary; a cut file makes it raise)."""
    with open(path, "rb") as f:
        reader = make_reader(f)
        assert reader.get_summary() is not None
        return [(ch.topic, m.log_time, m.data) for _, ch, m in reader.iter_messages(log_time_order=False)]


def test_recover_rebuilds_a_cut_file_into_a_complete_indexed_one(tmp_path: Path) -> None:
    path = tmp_path / "run.mcap"
    _write(path, n_scans=300, chunk_size=32 * 1024)
    full, _ = ml.read_log(path)
    with open(path, "rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None
    c = sorted(summary.chunk_indexes, key=lambda c: c.chunk_start_offset)[10]
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(path.read_bytes()[: c.chunk_start_offset + c.chunk_length // 2])  # mid-chunk, as a kill leaves it
    assert not mr.has_summary(cut)
    with open(cut, "rb") as f, pytest.raises(Exception):  # noqa: B017 (the library raises its own kinds)
        list(make_reader(f).iter_messages())
    before, _ = ml.read_log(cut)
    rec = mr.recover_log(cut)
    expected = [m for m in full if m.log_time_ns < c.message_start_time]
    assert rec.truncated and rec.messages == len(expected) == len(before) > 0
    assert rec.first_ns == T0 and rec.last_ns == max(m.log_time_ns for m in expected)
    assert "truncated at 2025-11-21T04:40:0" in rec.describe() and f"{len(expected)} messages" in rec.describe()
    # the same messages, bytes and times, now through the indexed reader; schemas decode as before
    assert _indexed(cut) == [(m.topic, m.log_time_ns, m.data) for m in expected]
    again, status = ml.read_log(cut)
    assert not status.truncated and [m.decode() for m in again[:5]] == [m.decode() for m in expected[:5]]
    info = mr.recovery_info(cut)
    assert info is not None and info["messages"] == str(len(expected)) and info["last_log_time_ns"] == str(rec.last_ns)
    assert not (tmp_path / "cut.mcap.recovering").exists()
    # a complete file is left as it is, and so is a recovered one
    data = path.read_bytes()
    done = mr.recover_log(path)
    assert not done.truncated and done.messages == len(full) and path.read_bytes() == data
    assert mr.recovery_info(path) is None
    recovered = cut.read_bytes()
    assert not mr.recover_log(cut).truncated and cut.read_bytes() == recovered


def test_recover_a_file_with_nothing_in_it(tmp_path: Path) -> None:
    empty = tmp_path / "empty.mcap"
    empty.write_bytes(b"")
    rec = mr.recover_log(empty)
    assert rec.messages == 0 and rec.truncated and "nothing was recovered" in rec.describe()
    header_only = tmp_path / "header.mcap"
    _write(tmp_path / "full.mcap", n_scans=10)
    header_only.write_bytes((tmp_path / "full.mcap").read_bytes()[:40])
    assert mr.recover_log(header_only).messages == 0
    assert header_only.read_bytes() == (tmp_path / "full.mcap").read_bytes()[:40]  # nothing to rebuild: untouched
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(b"not an mcap file at all")
    with pytest.raises(ml.McapLogError, match="not an MCAP"):
        mr.recover_log(junk)
