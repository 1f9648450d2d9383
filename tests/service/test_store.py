"""The SQLite result store: states, persistence across re-opening, restart recovery, schedules."""

from __future__ import annotations

from pathlib import Path

import pytest

from service.store import NotFound, Store, StoreError


def test_lifecycle_and_persistence(tmp_path: Path) -> None:
    db = tmp_path / "s.sqlite"
    s = Store(db)
    a = s.create_measurement({"target": "cylinder"})
    b = s.create_measurement({"target": "elbow"})
    c = s.create_measurement({"target": "cylinder"})
    assert [m.id for m in s.queued()] == [a.id, b.id, c.id]
    s.start(a.id)
    s.set_progress(a.id, 0.5, "sweeping")
    assert s.get(a.id).progress == 0.5 and s.get(a.id).message == "sweeping"
    s.set_paths(a.id, raw_path="/x/a.mcap")
    s.finish(a.id, {"diameter_m": 0.1375})
    s.start(b.id)
    s.fail(b.id, "motor fault: following error")
    with pytest.raises(StoreError, match="is done"):
        s.start(a.id)
    s.close()

    s2 = Store(db)  # re-open: everything is there
    assert s2.get(a.id).state == "done" and s2.get(a.id).result == {"diameter_m": 0.1375}
    assert s2.get(a.id).raw_path == "/x/a.mcap" and s2.get(a.id).progress == 1.0
    assert s2.get(b.id).state == "failed" and s2.get(b.id).error == "motor fault: following error"
    assert [m.id for m in s2.queued()] == [c.id]
    assert [m.id for m in s2.list_measurements()] == [c.id, b.id, a.id]
    assert [m.id for m in s2.list_measurements(state="done")] == [a.id]
    assert s2.count_by_state()["queued"] == 1
    with pytest.raises(StoreError, match="unknown state"):
        s2.list_measurements(state="sleeping")
    with pytest.raises(NotFound):
        s2.get("nope")


def test_restart_fails_running_and_keeps_queued(tmp_path: Path) -> None:
    db = tmp_path / "s.sqlite"
    s = Store(db)
    a = s.create_measurement({"n": 1})
    b = s.create_measurement({"n": 2})
    s.start(a.id)
    # the process dies here: no close, no finish
    s2 = Store(db)
    assert s2.recover_interrupted() == [a.id]
    assert s2.get(a.id).state == "failed" and "restart" in (s2.get(a.id).error or "")
    assert [m.id for m in s2.queued()] == [b.id]


def test_cancel(tmp_path: Path) -> None:
    s = Store(tmp_path / "s.sqlite")
    a = s.create_measurement({})
    s.cancel(a.id)
    assert s.get(a.id).state == "cancelled"
    with pytest.raises(StoreError, match="cancelled"):
        s.cancel(a.id)


def test_schedules(tmp_path: Path) -> None:
    db = tmp_path / "s.sqlite"
    s = Store(db)
    x = s.add_schedule({"target": "cylinder"}, cron="*/5 * * * *", next_run=100.0, name="every 5")
    y = s.add_schedule({"target": "elbow"}, interval_s=3600.0, next_run=50.0)
    with pytest.raises(StoreError, match="exactly one"):
        s.add_schedule({}, cron="* * * * *", interval_s=5.0)
    s.mark_schedule_run(x.id, 100.0, 400.0, "m1")
    s2 = Store(db)
    got = {sc.id: sc for sc in s2.list_schedules()}
    assert got[x.id].next_run == 400.0 and got[x.id].last_measurement_id == "m1" and got[x.id].cron == "*/5 * * * *"
    assert got[y.id].interval_s == 3600.0 and got[y.id].template == {"target": "elbow"}
    s2.delete_schedule(y.id)
    assert [sc.id for sc in s2.list_schedules()] == [x.id]
    with pytest.raises(NotFound):
        s2.delete_schedule(y.id)


def test_version_moves_with_every_write_from_any_connection(tmp_path: Path) -> None:
    db = tmp_path / "r.db"
    store, other = Store(db), Store(db)
    try:
        v0 = store.version
        m = store.create_measurement({"target": "cylinder"})
        v1 = store.version
        assert v1 != v0
        store.get(m.id)
        store.list_measurements()
        assert store.version == v1  # reads do not move it
        other.cancel(m.id)  # a write by another connection to the file
        v2 = store.version
        assert v2 != v1 and store.get(m.id).state == "cancelled"
    finally:
        store.close()
        other.close()
