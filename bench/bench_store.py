"""Benchmark of the result store (printed, never asserted): what SQLAlchemy costs per store call.

For a SQLite file, each operation of :class:`service.store.Store` against a baseline in the same
run: the same SQL on one plain ``sqlite3`` connection as the store before SQLAlchemy ran it (the
store's version as ``PRAGMA data_version``; a write as ``BEGIN IMMEDIATE`` ... ``COMMIT``), rows
made into the same ``Measurement`` objects (JSON decoded). Best of
``--repeat`` rounds of ``--calls`` calls, microseconds per call, and the ratio. With ``--url``, the
store's figures for that database too (e.g. a PostgreSQL server; no baseline there).

Run: ``.venv/bin/python -m bench.bench_store [--calls 300] [--repeat 3] [--url postgresql://...]``
"""

from __future__ import annotations

import argparse
import json
import sqlite3
import tempfile
import time
import timeit
import uuid
from collections.abc import Callable
from pathlib import Path

from service.db.engine import shown
from service.store import Store, _measurement


def _baseline(path: Path) -> dict[str, Callable[[], object]]:
    db = sqlite3.connect(path, isolation_level=None, check_same_thread=False)
    db.row_factory = sqlite3.Row
    db.execute("PRAGMA journal_mode=WAL")
    db.execute("PRAGMA synchronous=NORMAL")
    mid = db.execute("SELECT id FROM measurements ORDER BY seq DESC LIMIT 1").fetchone()[0]

    def create() -> object:
        new = uuid.uuid4().hex[:16]
        db.execute("BEGIN IMMEDIATE")
        seq = db.execute("SELECT COALESCE(MAX(seq), 0) + 1 FROM measurements").fetchone()[0]
        db.execute(
            "INSERT INTO measurements (id, seq, created_at, state, request, rig_id) VALUES (?, ?, ?, ?, ?, ?)",
            (new, seq, time.time(), "queued", json.dumps({"x": 1}), "bench"),
        )
        db.execute("COMMIT")
        return _measurement(db.execute("SELECT * FROM measurements WHERE id = ?", (new,)).fetchone())

    return {
        "version": lambda: db.execute("PRAGMA data_version").fetchone(),
        "get": lambda: _measurement(db.execute("SELECT * FROM measurements WHERE id = ?", (mid,)).fetchone()),
        "list 100": lambda: [
            _measurement(r) for r in db.execute("SELECT * FROM measurements ORDER BY seq DESC LIMIT 100")
        ],
        "create": create,
    }


def _store_ops(store: Store) -> dict[str, Callable[[], object]]:
    mid = store.list_measurements(limit=1)[0].id
    return {
        "version": lambda: store.version,
        "get": lambda: store.get(mid),
        "list 100": lambda: store.list_measurements(),
        "create": lambda: store.create_measurement({"x": 1}),
    }


def _time(fn: Callable[[], object], calls: int, repeat: int) -> float:
    return min(timeit.repeat(fn, number=calls, repeat=repeat)) / calls * 1e6


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--calls", type=int, default=300)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--url", help="also time the store on this database (its tables get 100+ rows)")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "bench.sqlite"
        store = Store(path, "bench")
        for i in range(100):
            store.create_measurement({"i": i})
        ops, base = _store_ops(store), _baseline(path)
        print(f"SQLite, {args.calls} calls x {args.repeat}, us per call (best round)")
        print(f"{'operation':10s} {'sqlite3':>9s} {'Store':>9s} {'ratio':>6s}")
        for name in ops:
            b, s = _time(base[name], args.calls, args.repeat), _time(ops[name], args.calls, args.repeat)
            print(f"{name:10s} {b:9.1f} {s:9.1f} {s / b:6.1f}")
        store.close()
    if args.url:
        other = Store(args.url, "bench")
        for i in range(100):
            other.create_measurement({"i": i})
        print(f"{shown(args.url)}: Store, us per call")
        for name, fn in _store_ops(other).items():
            print(f"{name:10s} {_time(fn, args.calls, args.repeat):9.1f}")
        other.close()


if __name__ == "__main__":
    main()
