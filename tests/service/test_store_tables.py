"""The stores beside the measurements (calibrations, recipes, result versions) on SQLite and on a real
PostgreSQL server (the ``db_url`` fixture): their round trips with the backends' own JSON and boolean
types, transactions that store all or nothing, and writers of several rigs at once (threads, each
with its own engine, as the services of two rigs would be) losing nothing and numbering nothing twice.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import Any

import numpy as np
import pytest
import sqlalchemy as sa

from lrms.calibration import CalibrationResult, Identifiability
from lrms.kinematics import RigModel
from service.calstore import CalibrationStore
from service.db.schema import calibrations, store_version
from service.recipes import Recipe
from service.recipestore import RecipeConflict, RecipeNotFound, RecipeStore
from service.store import NotFound, Store
from service.versionstore import VersionStore, VersionStoreError, calibration_id


def calibration(p: float = 0.1, **terms: float) -> CalibrationResult:
    n = len(RigModel.NAMES)
    return CalibrationResult(
        model=RigModel(p=p, **terms),
        nominal=RigModel(),
        covariance=np.zeros((n, n)),
        estimated=("p",),
        identifiability=Identifiability(held={}, rank=1, condition=1.0),
        surfaces=(),
        residuals={},
        artefact={},
        created="2026-01-01T00:00:00Z",
    )


def recipe(name: str, nominal: float = 0.1375) -> Recipe:
    return Recipe.model_validate(
        {
            "name": name,
            "target": "cylinder",
            "tolerances": {"diameter": {"nominal_m": nominal, "lower_m": -0.001, "upper_m": 0.001}},
        }
    )


def together(n: int, work: Callable[[int], None]) -> None:
    """``work(0)`` ... ``work(n - 1)`` in ``n`` threads released at once; re-raises the first error."""
    barrier = threading.Barrier(n)
    errors: list[BaseException] = []

    def run(i: int) -> None:
        try:
            barrier.wait(timeout=30)
            work(i)
        except BaseException as exc:  # handed to the test thread
            errors.append(exc)

    threads = [threading.Thread(target=run, args=(i,)) for i in range(n)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=120)
    assert not any(t.is_alive() for t in threads), "a writer hangs"
    if errors:
        raise errors[0]


def write_count(engine: sa.Engine) -> int:
    with engine.connect() as conn:
        return int(conn.execute(sa.select(store_version.c.n)).scalar_one())


# -- calibrations -------------------------------------------------------------------------------------


def test_calibrations_round_trip_and_one_active_per_rig(db_url: str) -> None:
    s = Store(db_url, "press-1")
    cs = CalibrationStore(s.engine)
    try:
        a = cs.add(calibration(0.1, k0=0.001), name="spring", comment="two-face sweep", rig_id="press-1")
        b = cs.add(calibration(0.2), name="summer", rig_id="press-1")
        c = cs.add(calibration(0.3), rig_id="press-2")
        d = cs.add(calibration(0.4))  # no rig: a rig of its own
        assert [x.id for x in cs.list()] == [d.id, c.id, b.id, a.id]  # newest first
        assert [x.id for x in cs.list(rig_id="press-1")] == [b.id, a.id]
        got = cs.get(a.id)
        assert (got.name, got.comment, got.rig_id, got.active) == ("spring", "two-face sweep", "press-1", False)
        assert got.calibration.model == RigModel(p=0.1, k0=0.001)  # the whole rig model comes back
        assert cs.active("press-1") is None and cs.active(None) is None
        before = write_count(s.engine)
        cs.activate(a.id)
        cs.activate(c.id)
        cs.activate(d.id)
        assert write_count(s.engine) == before + 3  # each write took the database's write lock
        assert cs.active("press-1").id == a.id and cs.active("press-2").id == c.id  # type: ignore[union-attr]
        assert cs.active(None).id == d.id  # type: ignore[union-attr]
        cs.activate(b.id)  # the rig's other calibration is deactivated, no other rig's
        assert cs.active("press-1").id == b.id and not cs.get(a.id).active  # type: ignore[union-attr]
        assert cs.get(c.id).active and cs.get(d.id).active
        with s.engine.connect() as conn:  # a real boolean column on both backends
            flags = dict(conn.execute(sa.select(calibrations.c.id, calibrations.c.active)).all())
        assert flags == {a.id: False, b.id: True, c.id: True, d.id: True}
        assert all(type(v) is bool for v in flags.values())
        with pytest.raises(NotFound):
            cs.get("0" * 16)
        with pytest.raises(NotFound):
            cs.activate("0" * 16)
    finally:
        s.close()


def test_calibrations_of_two_rigs_stored_and_activated_at_once(db_url: str) -> None:
    """Two services store and activate calibrations at the same time: every one is stored with its
    own sequence number, and each rig ends with exactly one active (the last it activated)."""
    stores = [Store(db_url, rig) for rig in ("press-1", "press-2")]
    n = 12
    last: dict[str, str] = {}

    def work(i: int) -> None:
        cs = CalibrationStore(stores[i].engine)
        rig = stores[i].rig_id
        for k in range(n):
            cid = cs.add(calibration(0.1 + 0.01 * k), name=f"{rig}-{k}", rig_id=rig).id
            cs.activate(cid)
            last[rig] = cid

    try:
        together(2, work)
        with stores[0].engine.connect() as conn:
            rows = conn.execute(sa.select(calibrations.c.seq, calibrations.c.rig_id, calibrations.c.active)).all()
        assert sorted(r.seq for r in rows) == list(range(1, 2 * n + 1))  # none numbered twice
        for rig in ("press-1", "press-2"):
            assert sum(r.active for r in rows if r.rig_id == rig) == 1
            assert CalibrationStore(stores[0].engine).active(rig).id == last[rig]  # type: ignore[union-attr]
    finally:
        for s in stores:
            s.close()


# -- recipes --------------------------------------------------------------------------------------------


def test_recipes_round_trip(db_url: str) -> None:
    s = Store(db_url, "press-1")
    rs = RecipeStore(s.engine)
    try:
        v1 = rs.create(recipe("SHAFT-1"))
        assert v1.version == 1 and not v1.retired
        with pytest.raises(RecipeConflict, match="exists already"):
            rs.create(recipe("SHAFT-1", 0.2))
        assert rs.versions("SHAFT-1") == [1]  # the refused create stored nothing
        v2 = rs.update(recipe("SHAFT-1", 0.14))
        assert v2.version == 2 and rs.latest("SHAFT-1").tolerances.diameter.nominal_m == 0.14  # type: ignore[union-attr]
        assert rs.version("SHAFT-1", 1).tolerances.diameter.nominal_m == 0.1375  # type: ignore[union-attr]
        rs.create(recipe("FLANGE-1"))
        assert rs.retire("FLANGE-1").retired
        assert [r.name for r in rs.list_recipes()] == ["SHAFT-1"]  # boolean filter on both backends
        assert [r.name for r in rs.list_recipes(include_retired=True)] == ["FLANGE-1", "SHAFT-1"]
        assert not rs.update(recipe("FLANGE-1")).retired  # a new version is in use again
        with pytest.raises(RecipeNotFound, match="no version 7"):
            rs.version("SHAFT-1", 7)
        with pytest.raises(RecipeNotFound):
            rs.update(recipe("NOPE"))
        rs.link("m1", "SHAFT-1", 1, "4711", "ana")
        rs.link("m2", "SHAFT-1", 2, "4712", None)
        assert [(p.measurement_id, p.version, p.operator) for p in rs.history("SHAFT-1")] == [
            ("m1", 1, "ana"),
            ("m2", 2, None),
        ]
        assert [p.part_id for p in rs.history("SHAFT-1", version=2)] == ["4712"]
    finally:
        s.close()


def test_recipe_versions_stored_by_two_rigs_at_once_are_numbered_in_turn(db_url: str) -> None:
    stores = [Store(db_url, rig) for rig in ("press-1", "press-2")]
    RecipeStore(stores[0].engine).create(recipe("SHAFT-2"))
    n = 10

    def work(i: int) -> None:
        rs = RecipeStore(stores[i].engine)
        for k in range(n):
            rs.update(recipe("SHAFT-2", 0.1 + 0.001 * (i * n + k)))
            rs.link(f"m-{i}-{k}", "SHAFT-2", 1, f"part-{i}-{k}", None)

    try:
        together(2, work)
        rs = RecipeStore(stores[0].engine)
        assert rs.versions("SHAFT-2") == list(range(1, 2 * n + 2))  # none refused, none lost
        assert rs.latest("SHAFT-2").version == 2 * n + 1
        nominals = {rs.version("SHAFT-2", v).tolerances.diameter.nominal_m for v in range(2, 2 * n + 2)}  # type: ignore[union-attr]
        assert len(nominals) == 2 * n
        assert len(rs.history("SHAFT-2")) == 2 * n
    finally:
        for s in stores:
            s.close()


# -- result versions ----------------------------------------------------------------------------------


def test_result_versions_round_trip_json_and_calibrations(db_url: str) -> None:
    s = Store(db_url, "press-1")
    vs = VersionStore(s.engine)
    result: dict[str, Any] = {
        "diameter_m": 0.13750000000000001,
        "uncertainty": {"expanded_m": 1.25e-4, "budget": [{"name": "k0", "u": 3e-5}]},
        "decision": None,
        "note": "Ø 137,5 mm – ok",
        "flags": [True, False],
        "n": 12345678901,
    }
    try:
        assert vs.add("m1", "a" * 64, "logged", "0.1.0", result) == 1
        assert vs.add("m1", "a" * 64, "logged", "0.1.0", {"diameter_m": 0.2}) is None
        assert vs.add("m1", "a" * 64, "logged", "0.2.0", {"diameter_m": 0.2}) == 2
        assert vs.add("m2", "b" * 64, "logged", "0.1.0", {"diameter_m": 0.3}) == 1
        got = vs.versions()
        assert [(v.measurement_id, v.version) for v in got] == [("m1", 1), ("m1", 2), ("m2", 1)]
        assert got[0].result == result  # the JSON column round-trips exactly (floats, text, booleans, nulls)
        assert [v.measurement_id for v in vs.versions(["m2", "m9"])] == ["m2"]
        assert vs.done_hashes(["m1", "m2", "m3"], "logged", "0.1.0") == {"m1": {"a" * 64}, "m2": {"b" * 64}}
        with pytest.raises(VersionStoreError, match="not finite JSON"):
            vs.add("m3", "c" * 64, "logged", "0.1.0", {"diameter_m": float("nan")})
        assert vs.versions(["m3"]) == []

        # calibrations: those kept by reprocess and those of the service's store, found by id prefix
        kept = calibration(0.25).to_dict()
        kid = vs.put_calibration(kept, source="/x/cal.json")
        assert kid == calibration_id(kept) and vs.put_calibration(kept) == kid  # kept once
        found = vs.find_calibration(kid[:8])
        assert (found.id, found.origin, found.rig_id) == (kid, "reprocess", None) and found.calibration == kept
        svc = CalibrationStore(s.engine).add(calibration(0.3, k1=2e-4), rig_id="press-2")
        found = vs.find_calibration(svc.id[:10])
        assert (found.id, found.origin, found.rig_id) == (svc.id, "service", "press-2")
        assert CalibrationResult.from_dict(found.calibration).model == RigModel(p=0.3, k1=2e-4)
        assert vs.get_calibration(svc.id) == (svc.id, found.calibration)
        with pytest.raises(VersionStoreError, match="no calibration"):
            vs.find_calibration("ffffffffff")
        with pytest.raises(VersionStoreError, match="no calibration"):
            vs.find_calibration("%%%%%%")  # LIKE wildcards are characters of an id, not patterns
        with pytest.raises(VersionStoreError, match="at least 6"):
            vs.find_calibration("abc")
    finally:
        s.close()


def test_result_versions_of_two_clients_at_once_lose_nothing(db_url: str) -> None:
    """Two ``lrms reprocess`` clients store versions of the same measurements at once (each with
    its own calibration, and once the same inputs): numbers 1..2n per measurement, each inputs once."""
    stores = [Store(db_url, rig) for rig in ("press-1", "press-2")]
    n = 8
    stored: list[list[int | None]] = [[], []]

    def work(i: int) -> None:
        vs = VersionStore(stores[i].engine)
        for k in range(n):
            for mid in ("m1", "m2"):
                stored[i].append(vs.add(mid, f"{k:064x}", f"cal-{i}", "0.1.0", {"k": k, "client": i}))
                stored[i].append(vs.add(mid, f"{k:064x}", "shared", "0.1.0", {"k": k}))

    try:
        together(2, work)
        got = VersionStore(stores[0].engine).versions()
        for mid in ("m1", "m2"):
            mine = [v for v in got if v.measurement_id == mid]
            assert sorted(v.version for v in mine) == list(range(1, 3 * n + 1))
            keys = [(v.raw_sha256, v.calibration_id) for v in mine]
            assert len(set(keys)) == len(keys) == 3 * n
        # the shared inputs: stored by one client, the other was told they were there
        assert sum(x is None for x in stored[0] + stored[1]) == 2 * n
    finally:
        for s in stores:
            s.close()
