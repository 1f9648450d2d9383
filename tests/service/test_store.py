"""The result store on SQLite and on a real PostgreSQL server: states, persistence across re-opening,
restart recovery, schedules, rig ids (per-rig queue, listing of all rigs), concurrent services of two
rigs on one database, the schema the migrations build, and a SQLite file of the pre-migration store
upgraded in place."""

from __future__ import annotations

import json
import sqlite3
import subprocess
import sys
import time
from pathlib import Path

import pytest
from alembic.autogenerate import compare_metadata
from alembic.runtime.migration import MigrationContext
from sqlalchemy import create_engine, func, inspect, select

from service.db import engine as db_engine
from service.db import migrate, schema
from service.db.schema import metadata, store_version
from service.store import NotFound, Store, StoreError
from tests.conftest import REPO
from tests.service.pgserver import PostgresServer


def test_lifecycle_and_persistence(db_url: str) -> None:
    s = Store(db_url, "rig-a")
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

    s2 = Store(db_url, "rig-a")  # re-open: everything is there
    assert s2.get(a.id).state == "done" and s2.get(a.id).result == {"diameter_m": 0.1375}
    assert s2.get(a.id).raw_path == "/x/a.mcap" and s2.get(a.id).progress == 1.0
    assert s2.get(a.id).rig_id == "rig-a"
    assert s2.get(b.id).state == "failed" and s2.get(b.id).error == "motor fault: following error"
    assert [m.id for m in s2.queued()] == [c.id]
    assert [m.id for m in s2.list_measurements()] == [c.id, b.id, a.id]
    assert [m.id for m in s2.list_measurements(state="done")] == [a.id]
    assert s2.count_by_state()["queued"] == 1
    with pytest.raises(StoreError, match="unknown state"):
        s2.list_measurements(state="sleeping")
    with pytest.raises(NotFound):
        s2.get("nope")
    s2.close()


def test_restart_fails_running_and_keeps_queued(db_url: str) -> None:
    s = Store(db_url, "rig-a")
    a = s.create_measurement({"n": 1})
    b = s.create_measurement({"n": 2})
    s.start(a.id)
    # the process dies here: no close, no finish
    s2 = Store(db_url, "rig-a")
    assert s2.recover_interrupted() == [a.id]
    assert s2.get(a.id).state == "failed" and "restart" in (s2.get(a.id).error or "")
    assert [m.id for m in s2.queued()] == [b.id]
    s.close()
    s2.close()


def test_fail_interrupted_keeps_paths_unless_given(db_url: str) -> None:
    s = Store(db_url, "rig-a")
    a, b = s.create_measurement({}), s.create_measurement({})
    for m in (a, b):
        s.start(m.id)
        s.set_paths(m.id, raw_path=f"/x/{m.id}.mcap", cloud_path=f"/x/{m.id}.ply")
    s.fail_interrupted(a.id)
    s.fail_interrupted(b.id, "died", raw_path="/y/b.mcap", raw_truncated=True)
    ga, gb = s.get(a.id), s.get(b.id)
    assert (ga.raw_path, ga.cloud_path, ga.raw_truncated) == (f"/x/{a.id}.mcap", f"/x/{a.id}.ply", False)
    assert (gb.raw_path, gb.cloud_path, gb.raw_truncated, gb.error) == ("/y/b.mcap", f"/x/{b.id}.ply", True, "died")
    s.close()


def test_cancel(db_url: str) -> None:
    s = Store(db_url, "rig-a")
    a = s.create_measurement({})
    s.cancel(a.id)
    assert s.get(a.id).state == "cancelled"
    with pytest.raises(StoreError, match="cancelled"):
        s.cancel(a.id)
    s.close()


def test_schedules(db_url: str) -> None:
    s = Store(db_url, "rig-a")
    x = s.add_schedule({"target": "cylinder"}, cron="*/5 * * * *", next_run=100.0, name="every 5")
    y = s.add_schedule({"target": "elbow"}, interval_s=3600.0, next_run=50.0)
    with pytest.raises(StoreError, match="exactly one"):
        s.add_schedule({}, cron="* * * * *", interval_s=5.0)
    s.mark_schedule_run(x.id, 100.0, 400.0, "m1")
    s2 = Store(db_url, "rig-a")
    got = {sc.id: sc for sc in s2.list_schedules()}
    assert got[x.id].next_run == 400.0 and got[x.id].last_measurement_id == "m1" and got[x.id].cron == "*/5 * * * *"
    assert got[y.id].interval_s == 3600.0 and got[y.id].template == {"target": "elbow"}
    assert got[y.id].enabled and got[y.id].rig_id == "rig-a"
    s2.delete_schedule(y.id)
    assert [sc.id for sc in s2.list_schedules()] == [x.id]
    with pytest.raises(NotFound):
        s2.delete_schedule(y.id)
    s.close()
    s2.close()


def test_version_moves_with_every_write_from_any_connection(db_url: str) -> None:
    store, other = Store(db_url, "rig-a"), Store(db_url, "rig-a")
    try:
        v0 = store.version
        m = store.create_measurement({"target": "cylinder"})
        v1 = store.version
        assert v1 != v0
        store.get(m.id)
        store.list_measurements()
        assert store.version == v1  # reads do not move it
        other.cancel(m.id)  # a write by another connection to the database
        v2 = store.version
        assert v2 != v1 and store.get(m.id).state == "cancelled"
    finally:
        store.close()
        other.close()


def test_rigs_share_a_database_with_a_queue_each(db_url: str) -> None:
    a, b = Store(db_url, "press-1"), Store(db_url, "press-2")
    a1 = a.create_measurement({"n": 1})
    b1 = b.create_measurement({"n": 2})
    a2 = a.create_measurement({"n": 3})
    assert [m.id for m in a.queued()] == [a1.id, a2.id]  # each rig runs its own queue only
    assert [m.id for m in b.queued()] == [b1.id]
    assert a.count_by_state()["queued"] == 2 and b.count_by_state()["queued"] == 1
    # the listing shows every rig, newest first, or one rig on request
    assert [(m.id, m.rig_id) for m in b.list_measurements()] == [
        (a2.id, "press-1"),
        (b1.id, "press-2"),
        (a1.id, "press-1"),
    ]
    assert [m.id for m in a.list_measurements(rig="press-2")] == [b1.id]
    assert a.list_measurements(rig="press-9") == []
    # a rig reads another's measurement but does not change it
    assert b.get(a1.id).rig_id == "press-1"
    for change in (b.start, b.cancel):
        with pytest.raises(StoreError, match="belongs to rig 'press-1'"):
            change(a1.id)
    assert a.get(a1.id).state == "queued"
    # a dead process of rig a leaves a running measurement: rig b's start-up does not touch it
    a.start(a1.id)
    assert b.interrupted() == [] and b.recover_interrupted() == []
    assert a.interrupted() == [a1.id]
    # schedules: each rig's own, listed together
    sa = a.add_schedule({"n": 1}, interval_s=60.0)
    sb = b.add_schedule({"n": 2}, interval_s=60.0)
    assert [s.id for s in a.list_schedules(rig="press-1")] == [sa.id]
    assert {s.id for s in a.list_schedules()} == {sa.id, sb.id}
    with pytest.raises(StoreError, match="belongs to rig 'press-2'"):
        a.delete_schedule(sb.id)
    b.mark_schedule_run(sa.id, 1.0, 2.0, "x")  # another rig's schedule: nothing changes
    assert a.get_schedule(sa.id).last_run is None
    a.close()
    b.close()


def test_bad_rig_id_and_url_are_refused(tmp_path: Path) -> None:
    with pytest.raises(StoreError, match="rig id 'a b'"):
        Store(tmp_path / "s.sqlite", "a b")
    with pytest.raises(StoreError, match="unsupported database 'mysql'"):
        Store("mysql://u@h/db", "r")
    with pytest.raises(StoreError, match="cannot open result store"):
        Store(tmp_path, "r")  # a folder, not a file


def test_the_migrations_build_the_schema(db_url: str) -> None:
    """What the migrations create is what service.db.schema declares (Alembic's comparison: tables,
    columns, types, nullability, indexes)."""
    s = Store(db_url, "rig-a")
    with s.engine.connect() as conn:
        diff = compare_metadata(MigrationContext.configure(conn), metadata)
        version = conn.execute(select(store_version.c.n)).scalars().all()
    assert diff == []
    assert migrate.current(s.engine) == migrate.head()
    assert version == [0]  # one row, no write yet
    s.close()


def test_concurrent_services_of_two_rigs_lose_nothing(db_url: str) -> None:
    """Two processes, one per rig, write to one database at once: every measurement, state change
    and schedule run of both is there, the queue order has no duplicate, and the write counter
    counts every write transaction of both (an increment lost to a race would show here)."""
    n = 60
    # the two open the new database at the same moment: it is migrated once, under the lock
    start_at = time.time() + 3.0
    procs = [
        subprocess.Popen(
            [sys.executable, "-m", "tests.service.storeworker", db_url, rig, str(n), str(start_at)],
            cwd=REPO,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        for rig in ("press-1", "press-2")
    ]
    writes = 0
    for p in procs:
        out, err = p.communicate(timeout=100)
        assert p.returncode == 0, err
        writes += int(out.split()[-1])
    s = Store(db_url, "press-1")
    ms = s.list_measurements(limit=1000)
    assert len(ms) == 2 * n
    for rig in ("press-1", "press-2"):
        mine = [m for m in ms if m.rig_id == rig]
        assert sorted(m.request["i"] for m in mine) == list(range(n))
        assert all(m.request["rig"] == rig for m in mine)
        done = [m for m in mine if m.state == "done"]
        assert len(done) == n - n // 5 and all(m.progress == 1.0 and m.result == {"i": m.request["i"]} for m in done)
        assert sum(m.state == "cancelled" for m in mine) == n // 5
    with s.engine.connect() as conn:
        seqs = conn.execute(select(metadata.tables["measurements"].c.seq)).scalars().all()
        counter = conn.execute(select(store_version.c.n)).scalar_one()
    assert len(set(seqs)) == len(seqs) == 2 * n
    assert counter == writes
    scheds = {sc.rig_id: sc for sc in s.list_schedules()}
    assert set(scheds) == {"press-1", "press-2"}
    assert all(sc.last_run == float(n - 2) for sc in scheds.values())  # the last run that was not cancelled
    s.close()


# -- the SQLite file of the store before migrations -------------------------------------------------

#: The schema the store created up to commit 03908b3 (its ``_SCHEMA``, verbatim).
OLD_SCHEMA = """
CREATE TABLE IF NOT EXISTS measurements (
    id TEXT PRIMARY KEY,
    seq INTEGER NOT NULL,
    created_at REAL NOT NULL,
    started_at REAL,
    finished_at REAL,
    state TEXT NOT NULL,
    request TEXT NOT NULL,
    progress REAL NOT NULL DEFAULT 0,
    message TEXT NOT NULL DEFAULT '',
    result TEXT,
    error TEXT,
    raw_path TEXT,
    cloud_path TEXT,
    schedule_id TEXT,
    raw_truncated INTEGER NOT NULL DEFAULT 0
);
CREATE INDEX IF NOT EXISTS measurements_state ON measurements(state, seq);
CREATE TABLE IF NOT EXISTS schedules (
    id TEXT PRIMARY KEY,
    created_at REAL NOT NULL,
    name TEXT NOT NULL DEFAULT '',
    cron TEXT,
    interval_s REAL,
    template TEXT NOT NULL,
    enabled INTEGER NOT NULL DEFAULT 1,
    next_run REAL,
    last_run REAL,
    last_measurement_id TEXT
);
"""


def old_store(path: Path, with_raw_truncated: bool = True) -> None:
    """A file as that store left it: WAL journal, five measurements in every state, two schedules."""
    schema = OLD_SCHEMA
    if not with_raw_truncated:  # a file older still: the store added this column to it itself
        schema = OLD_SCHEMA.replace(",\n    raw_truncated INTEGER NOT NULL DEFAULT 0", "")
        assert "raw_truncated" not in schema
    db = sqlite3.connect(path, isolation_level=None)
    db.execute("PRAGMA journal_mode=WAL")
    db.executescript(schema)
    rows = [
        ("m1", 1, 10.0, 11.0, 20.0, "done", {"target": "cylinder"}, 1.0, "done", {"diameter_m": 0.1375}, None),
        ("m2", 2, 30.0, 31.0, 32.0, "failed", {"target": "elbow"}, 0.2, "failed", None, "motor fault"),
        ("m3", 3, 40.0, None, 41.0, "cancelled", {}, 0.0, "cancelled", None, "cancelled by request"),
        ("m4", 4, 50.0, 51.0, None, "running", {"n": 4}, 0.5, "sweeping", None, None),
        ("m5", 5, 60.0, None, None, "queued", {"n": 5}, 0.0, "", None, None),
    ]
    for mid, seq, created, started, finished, state, req, prog, msg, result, error in rows:
        db.execute(
            "INSERT INTO measurements (id, seq, created_at, started_at, finished_at, state, request, progress, "
            "message, result, error, raw_path, schedule_id) VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?)",
            (
                mid,
                seq,
                created,
                started,
                finished,
                state,
                json.dumps(req),
                prog,
                msg,
                json.dumps(result) if result is not None else None,
                error,
                f"/data/raw/{mid}.mcap" if state == "done" else None,
                "s1" if mid == "m1" else None,
            ),
        )
    if with_raw_truncated:
        db.execute("UPDATE measurements SET raw_truncated = 1 WHERE id = 'm2'")
    db.execute(
        "INSERT INTO schedules (id, created_at, name, cron, template, next_run, last_run, last_measurement_id) "
        "VALUES ('s1', 5.0, 'hourly', '0 * * * *', '{\"target\": \"cylinder\"}', 3600.0, 0.0, 'm1')"
    )
    db.execute(
        "INSERT INTO schedules (id, created_at, interval_s, template, enabled) VALUES ('s2', 6.0, 60.0, '{}', 0)"
    )
    db.close()


#: The tables the migrations after the old store added (0003 calibrations, 0004 recipes, 0005 result versions).
NEW_TABLES = [
    (t.name, t)
    for t in (
        schema.calibrations,
        schema.recipes,
        schema.recipe_versions,
        schema.recipe_measurements,
        schema.result_versions,
        schema.reprocess_calibrations,
    )
]


@pytest.mark.parametrize("with_raw_truncated", [True, False], ids=["03908b3", "before-raw_truncated"])
def test_a_sqlite_file_of_the_old_store_upgrades_in_place(tmp_path: Path, with_raw_truncated: bool) -> None:
    path = tmp_path / "lrms.sqlite"
    old_store(path, with_raw_truncated)
    engine = create_engine(f"sqlite:///{path}")
    assert migrate.current(engine) is None  # never migrated
    engine.dispose()

    s = Store(path, "press-3")  # opening migrates it
    assert migrate.current(s.engine) == migrate.head()
    ms = {m.id: m for m in s.list_measurements()}
    assert [m.id for m in s.list_measurements()] == ["m5", "m4", "m3", "m2", "m1"]  # order kept
    assert all(m.rig_id == "press-3" for m in ms.values())  # the old rows are the upgrading rig's
    assert ms["m1"].result == {"diameter_m": 0.1375} and ms["m1"].raw_path == "/data/raw/m1.mcap"
    assert (ms["m1"].created_at, ms["m1"].started_at, ms["m1"].finished_at) == (10.0, 11.0, 20.0)
    assert ms["m1"].schedule_id == "s1" and ms["m2"].error == "motor fault" and ms["m2"].progress == 0.2
    assert ms["m2"].raw_truncated is with_raw_truncated and not ms["m1"].raw_truncated
    assert [m.id for m in s.queued()] == ["m5"] and s.interrupted() == ["m4"]
    sc = {x.id: x for x in s.list_schedules(rig="press-3")}
    assert sc["s1"].cron == "0 * * * *" and sc["s1"].last_measurement_id == "m1" and sc["s1"].enabled
    assert sc["s2"].interval_s == 60.0 and not sc["s2"].enabled and sc["s2"].name == ""
    with s.engine.connect() as conn:
        assert compare_metadata(MigrationContext.configure(conn), metadata) == []
        # every table of the head schema is there; those the file did not have are new and empty
        assert set(inspect(conn).get_table_names()) == set(metadata.tables) | {"alembic_version"}
        assert {name: conn.execute(select(func.count()).select_from(t)).scalar_one() for name, t in NEW_TABLES} == {
            name: 0 for name, _ in NEW_TABLES
        }
        assert conn.execute(select(store_version.c.id, store_version.c.n)).all() == [(1, 0)]
    assert migrate.head() == "0005"  # this test follows the migrations to the newest: extend it with each
    assert migrate.head() == migrate.HEAD  # the store skips Alembic at HEAD: it must name the newest script
    # and it goes on as a store: the queue continues after the old rows, under the rig id
    new = s.create_measurement({"n": 6})
    assert [m.id for m in s.queued()] == ["m5", new.id] and s.get(new.id).rig_id == "press-3"
    s.close()
    # a second opening (another rig) finds it at the head revision and changes no row
    other = Store(path, "press-4")
    assert {m.rig_id for m in other.list_measurements()} == {"press-3"}
    other.close()


def test_lrms_db_upgrade_migrates_the_configured_store(tmp_path: Path) -> None:
    path = tmp_path / "data" / "lrms.sqlite"
    path.parent.mkdir()
    old_store(path)
    cfg = tmp_path / "rig.toml"
    cfg.write_text('[sim]\n[storage]\ndir = "data"\nrig_id = "press-5"\n')
    proc = subprocess.run(
        [sys.executable, "-m", "service.cli.main", "db", "upgrade", "--config", str(cfg)],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert proc.returncode == 0, proc.stderr
    assert f"at revision {migrate.head()}" in proc.stdout and "(was none)" in proc.stdout
    engine = db_engine.create(f"sqlite:///{path}")
    assert migrate.current(engine) == migrate.head()
    engine.dispose()
    s = Store(path, "press-5")
    assert len(s.list_measurements()) == 5 and {m.rig_id for m in s.list_measurements()} == {"press-5"}
    s.close()


def test_lrms_db_upgrade_builds_an_empty_postgresql_database(tmp_path: Path, postgres_server: PostgresServer) -> None:
    """``lrms db upgrade`` with ``[storage] url`` naming a new, empty PostgreSQL database: every
    migration runs (0001 to the head), the schema is the declared one, every table is empty; a
    second run finds it at the head."""
    url = postgres_server.new_database()
    cfg = tmp_path / "rig.toml"
    cfg.write_text(f'[sim]\n[storage]\ndir = "data"\nurl = "{url}"\nrig_id = "press-6"\n')
    upgrade = [sys.executable, "-m", "service.cli.main", "db", "upgrade", "--config", str(cfg)]
    proc = subprocess.run(upgrade, capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr
    assert f"at revision {migrate.head()} (was none)" in proc.stdout and "rig id press-6" in proc.stdout
    engine = db_engine.create(url)
    try:
        assert engine.dialect.name == "postgresql"
        with engine.connect() as conn:
            assert compare_metadata(MigrationContext.configure(conn), metadata) == []
            assert set(inspect(conn).get_table_names()) == set(metadata.tables) | {"alembic_version"}
            counts = {
                t.name: conn.execute(select(func.count()).select_from(t)).scalar_one() for t in metadata.sorted_tables
            }
            assert counts == {t.name: (1 if t is store_version else 0) for t in metadata.sorted_tables}
    finally:
        engine.dispose()
    again = subprocess.run(upgrade, capture_output=True, text=True, timeout=60)
    assert again.returncode == 0, again.stderr
    assert f"at revision {migrate.head()} (was {migrate.head()})" in again.stdout
    assert not (tmp_path / "data" / "lrms.sqlite").exists()  # the URL, not the folder's SQLite file
