"""Re-processing archived raw logs on Dask (``lrms reprocess``).

Every ``done`` measurement of the result store (optionally created since and until a date, of
one rig, of one recipe) is re-fitted from its raw MCAP log: decode, mapping, fit and uncertainty,
the decision when the result has one (:func:`service.replay.replay`, the code of the live rig),
optionally with another rig calibration (a file, or the id of one kept before or of the service's
calibration store: :func:`resolve_calibration`). One measurement is one task
(:func:`reprocess_one`, a plain function of a picklable :class:`Task`) on a Dask cluster: a
:class:`distributed.LocalCluster` on this machine
(worker processes of one thread each, on 127.0.0.1) or an existing cluster by its scheduler's
address; ``workers=0`` runs the same function in this process (the serial baseline).

Raw logs are read through fsspec where they are archived (``archive``: a directory or any fsspec
URL, the log found by the file name the rig gave it; without ``archive``, the path the store
holds). The task reads the log once, hashes it (SHA-256) and fits it; a task whose inputs are
already stored (:mod:`service.versionstore`) returns "skipped" without fitting. Results are
written by this process as they arrive, so an interrupted run keeps what it finished and the
next run resumes. A task never raises: a log that cannot be read, is cut short or does not fit
is a failed task with its reason.
"""

from __future__ import annotations

import datetime as dt
import hashlib
import io
import json
import os
import sys
import time
from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path, PurePosixPath, PureWindowsPath
from typing import Any, Literal, TextIO

from sqlalchemy import Engine

from service.config import RigConfig
from service.errors import ServiceError
from service.versionstore import LOGGED_CALIBRATION, VersionStore, VersionStoreError

Status = Literal["done", "skipped", "failed"]


class ReprocessError(ServiceError):
    pass


def result_engine(config: RigConfig) -> Engine:
    """The SQLAlchemy engine of the result store (``[storage] url``: SQLite or PostgreSQL), opened
    (and migrated) as the service opens it."""
    from service.store import Store

    return Store(config.storage.db_url, config.storage.rig_id).engine


@dataclass(frozen=True)
class Archived:
    """A measurement to re-process: its id, creation time, raw-log path, and what the summary
    compares of its original result (diameter, decision; the whole result stays in the store: an
    archive of millions of results would not fit in memory)."""

    measurement_id: str
    created_at: float
    raw_path: str
    original_diameter_m: float | None = None
    original_decision: str | None = None
    part: dict[str, Any] | None = None
    """A recipe measurement's part (``part_id``, ``operator``, ``part_temperature_c``,
    ``temperature_uncertainty_c``), from its original result; None for a free-form measurement."""
    recipe: dict[str, Any] | None = None
    """The recipe version it was measured with (JSON), to decide the re-fitted result again."""
    recipe_version: int | None = None


def parse_since(value: str, flag: str = "--since") -> float:
    """``--since`` / ``--until``: an ISO date or date-time (UTC when it names no zone) as s since the epoch."""
    try:
        t = dt.datetime.fromisoformat(value)
    except ValueError:
        raise ReprocessError(f"{flag} {value!r}: not an ISO date (2026-01-31 or 2026-01-31T08:00)") from None
    if t.tzinfo is None:
        t = t.replace(tzinfo=dt.UTC)
    return t.timestamp()


def archived_measurements(
    engine: Engine,
    since: float | None = None,
    recipe: str | None = None,
    *,
    until: float | None = None,
    rig: str | None = None,
) -> list[Archived]:
    """Finished measurements with a raw log, oldest first: created at ``since`` or later and before
    ``until`` (s since the epoch), of rig ``rig`` (its ``rig_id``), of ``recipe`` (the request's
    ``recipe``)."""
    from sqlalchemy import select

    from service.db.schema import measurements as M

    q = select(M.c.id, M.c.created_at, M.c.request, M.c.result, M.c.raw_path).where(
        M.c.state == "done", M.c.raw_path.is_not(None)
    )
    if since is not None:
        q = q.where(M.c.created_at >= since)
    if until is not None:
        q = q.where(M.c.created_at < until)
    if rig is not None:
        q = q.where(M.c.rig_id == rig)
    q = q.order_by(M.c.created_at, M.c.id)
    with engine.connect() as conn:
        rows = conn.execute(q).all()
    out = []
    recipes: dict[tuple[str, int], dict[str, Any]] = {}
    for mid, created, request, result, raw_path in rows:
        req = _json(request)
        if req.get("target") == "calibration":  # a calibration sweep: no part was measured
            continue
        if recipe is not None and req.get("recipe") != recipe:
            continue
        original = _json(result) if result is not None else None
        part, recipe_json, version = _part_of(engine, original, recipes)
        out.append(
            Archived(
                str(mid),
                float(created),
                str(raw_path),
                diameter_and_u(original)[0],
                decision_of(original),
                part,
                recipe_json,
                version,
            )
        )
    return out


def _part_of(
    engine: Engine, original: dict[str, Any] | None, cache: dict[tuple[str, int], dict[str, Any]]
) -> tuple[dict[str, Any] | None, dict[str, Any] | None, int | None]:
    """A recipe measurement's part fields and its recipe version (from the recipe store), else Nones."""
    part = (original or {}).get("part")
    if not isinstance(part, dict) or "recipe" not in part or "recipe_version" not in part:
        return None, None, None
    key = (str(part["recipe"]), int(part["recipe_version"]))
    if key not in cache:
        from service.recipes import Recipe
        from service.recipestore import RecipeStore

        stored = RecipeStore(engine).version(*key)  # the recipe with its version's own fields
        cache[key] = stored.model_dump(mode="json", include=set(Recipe.model_fields))
    thermal = (original or {}).get("thermal") or {}
    fields = {
        "part_id": part.get("part_id"),
        "operator": part.get("operator"),
        "part_temperature_c": thermal.get("part_temperature_c"),
        "temperature_uncertainty_c": thermal.get("temperature_uncertainty_c"),
    }
    return fields, cache[key], key[1]


def _json(value: Any) -> dict[str, Any]:
    data = json.loads(value) if isinstance(value, str | bytes) else value
    return data if isinstance(data, dict) else {}


def log_url(archive: str | None, raw_path: str) -> str:
    """Where a raw log is read: ``archive`` joined with the log's file name, else ``raw_path``."""
    if archive is None:
        return raw_path
    name = PureWindowsPath(raw_path).name if "\\" in raw_path else PurePosixPath(raw_path).name
    return f"{archive.rstrip('/')}/{name}"


@dataclass(frozen=True)
class Task:
    """One measurement to re-fit (picklable: it travels to a Dask worker)."""

    measurement_id: str
    url: str
    software_version: str
    calibration_id: str = LOGGED_CALIBRATION
    kinematics: dict[str, Any] | None = None
    """``[kinematics]`` keys replacing the logged ones (None: the rig model in the log)."""
    done_hashes: frozenset[str] = frozenset()
    """Raw-log hashes of this measurement already evaluated with this calibration and software."""
    part: dict[str, Any] | None = None
    recipe: dict[str, Any] | None = None
    recipe_version: int | None = None
    """A recipe measurement: its part and recipe version, decided again on the re-fitted result."""


@dataclass(frozen=True)
class Outcome:
    measurement_id: str
    status: Status
    raw_sha256: str | None = None
    result: dict[str, Any] | None = None
    reason: str = ""
    cpu_s: float = 0.0
    """CPU time of the task (read, hash, decode, mapping, fit) in its process."""


def reprocess_one(task: Task) -> Outcome:
    """Read, hash and re-fit one raw log (runs on a worker; never raises)."""
    t0 = time.process_time()

    def failed(reason: str, sha: str | None = None) -> Outcome:
        return Outcome(task.measurement_id, "failed", sha, None, reason, time.process_time() - t0)

    try:
        from lrms import __version__

        if __version__ != task.software_version:
            return failed(f"the worker runs lrms {__version__}, the run asks for {task.software_version}")
        import fsspec

        with fsspec.open(task.url, "rb") as fh:
            data: bytes = fh.read()
        sha = hashlib.sha256(data).hexdigest()
        if sha in task.done_hashes:
            return Outcome(task.measurement_id, "skipped", sha, None, "already stored", time.process_time() - t0)
        from service.replay import replay

        out = replay(io.BytesIO(data), kinematics=task.kinematics)
        if out["truncated"]:
            return failed(f"the raw log {task.url} is cut short: not re-fitted", sha)
        result = out["result"]
        if task.recipe is not None and task.part is not None and task.recipe_version is not None:
            from service.parts import part_result
            from service.recipes import Recipe

            recipe = Recipe.model_validate(task.recipe)
            result = {**result, **part_result(result, task.part, recipe, task.recipe_version)}
        return Outcome(task.measurement_id, "done", sha, result, "", time.process_time() - t0)
    except FileNotFoundError as exc:
        return failed(f"raw log not found: {exc}")
    except Exception as exc:  # one bad log is one failed task, never the end of the run
        reason = str(exc) if isinstance(exc, ServiceError) else f"{type(exc).__name__}: {exc}"
        return failed(reason or type(exc).__name__)


# -- executors ----------------------------------------------------------------------------
Executor = Callable[[list[Task]], Iterator[Outcome]]


def serial_executor(tasks: list[Task]) -> Iterator[Outcome]:
    """The tasks one after another in this process (the baseline; and ``--workers 0``)."""
    for task in tasks:
        yield reprocess_one(task)


def dask_executor(client: Any, window: int | None = None) -> Executor:
    """The tasks on ``client``'s cluster, at most ``window`` in flight (default: 4 per worker
    thread, at least 16), results in the order they finish. A task whose worker died is failed."""
    from distributed import as_completed

    def run(tasks: list[Task]) -> Iterator[Outcome]:
        if not tasks:
            return
        threads = sum(client.nthreads().values()) or 1
        size = window if window is not None else max(16, 4 * threads)
        pending = iter(tasks)
        by_key: dict[str, Task] = {}
        batch = os.urandom(4).hex()

        def submit(task: Task) -> Any:
            key = f"lrms-reprocess-{task.measurement_id}-{batch}"
            by_key[key] = task
            return client.submit(reprocess_one, task, key=key, pure=False, retries=0)

        ac = as_completed([submit(t) for _, t in zip(range(size), pending, strict=False)])
        for fut in ac:
            task = by_key.pop(fut.key)
            if fut.status == "finished":
                yield fut.result()
            else:
                exc = fut.exception()
                yield Outcome(task.measurement_id, "failed", None, None, f"task lost: {type(exc).__name__}: {exc}")
            fut.release()
            nxt = next(pending, None)
            if nxt is not None:
                ac.add(submit(nxt))

    return run


@contextmanager
def dask_client(scheduler: str | None = None, workers: int = 2) -> Iterator[Any]:
    """A client of the cluster at ``scheduler``, or of a new :class:`distributed.LocalCluster` on
    127.0.0.1 with ``workers`` processes of one thread each (no dashboard)."""
    from distributed import Client, LocalCluster

    if scheduler is not None:
        try:
            client = Client(scheduler, timeout=30)
        except OSError as exc:
            raise ReprocessError(f"cannot reach the Dask scheduler {scheduler}: {exc}") from None
        with client:
            yield client
        return
    if workers < 1:
        raise ReprocessError("a local Dask cluster needs at least one worker")
    for var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(var, "1")  # the worker processes inherit it: one BLAS thread each
    with (
        LocalCluster(
            n_workers=workers,
            threads_per_worker=1,
            processes=True,
            host="127.0.0.1",
            dashboard_address=None,
            silence_logs=40,  # logging.ERROR
        ) as cluster,
        Client(cluster) as client,
    ):
        yield client


# -- the run ------------------------------------------------------------------------------
@dataclass
class Summary:
    total: int = 0
    done: int = 0
    skipped: int = 0
    failed: list[dict[str, str]] = field(default_factory=list)
    diameter_changes: list[dict[str, Any]] = field(default_factory=list)
    """Re-fits whose diameter moved from the original by more than the new expanded U."""
    decision_changes: list[dict[str, Any]] = field(default_factory=list)
    cpu_s: float = 0.0
    wall_s: float = 0.0
    calibration_id: str = LOGGED_CALIBRATION
    software_version: str = ""

    def to_dict(self) -> dict[str, Any]:
        return {
            "total": self.total,
            "done": self.done,
            "skipped": self.skipped,
            "failed": self.failed,
            "diameter_changes": self.diameter_changes,
            "decision_changes": self.decision_changes,
            "cpu_s": self.cpu_s,
            "wall_s": self.wall_s,
            "calibration_id": self.calibration_id,
            "software_version": self.software_version,
        }

    def text(self) -> str:
        lines = [
            f"{self.total} measurements: {self.done} re-fitted, {self.skipped} skipped (already stored), "
            f"{len(self.failed)} failed; calibration {self.calibration_id}, lrms {self.software_version}; "
            f"{self.wall_s:.1f} s wall, {self.cpu_s:.1f} s CPU in the tasks"
        ]
        lines += [f"  failed {f['measurement_id']}: {f['reason']}" for f in self.failed]
        lines.append(f"{len(self.diameter_changes)} diameters moved by more than U:")
        lines += [
            f"  {c['measurement_id']}: {c['original_m'] * 1e3:.3f} -> {c['new_m'] * 1e3:.3f} mm"
            f" (U {c['u_m'] * 1e3:.3f} mm)"
            for c in self.diameter_changes
        ]
        lines.append(f"{len(self.decision_changes)} decisions changed:")
        lines += [f"  {c['measurement_id']}: {c['original']} -> {c['new']}" for c in self.decision_changes]
        return "\n".join(lines)


def diameter_and_u(result: dict[str, Any] | None) -> tuple[float | None, float | None]:
    """A cylinder result's diameter and expanded uncertainty U (None where it has none)."""
    if not result:
        return None, None
    d = result.get("diameter_m")
    u = (result.get("uncertainty") or {}).get("expanded_m")
    return (float(d) if isinstance(d, int | float) else None, float(u) if isinstance(u, int | float) else None)


def decision_of(result: dict[str, Any] | None) -> str | None:
    """A result's conformity decision: ``decision`` (a string, or an object with ``outcome``, as
    :mod:`service.parts` writes it, or ``decision``) or ``conformity.decision``; None when it has none."""
    if not result:
        return None
    for holder in (result, result.get("conformity")):
        if not isinstance(holder, dict):
            continue
        d = holder.get("decision")
        if isinstance(d, dict):
            d = d.get("outcome", d.get("decision"))
        if isinstance(d, str):
            return d
    return None


def progress_bar(stream: TextIO = sys.stderr, width: int = 30) -> Callable[[Summary], None]:
    """A one-line text progress bar (``\\r``-rewritten) on ``stream``."""

    def show(s: Summary) -> None:
        n = s.done + s.skipped + len(s.failed)
        frac = n / s.total if s.total else 1.0
        bar = "#" * round(frac * width)
        stream.write(
            f"\r[{bar:.<{width}}] {n}/{s.total}: {s.done} re-fitted, {s.skipped} skipped, {len(s.failed)} failed"
            + ("\n" if n == s.total else "")
        )
        stream.flush()

    return show


def reprocess(
    store: VersionStore,
    measurements: Iterable[Archived],
    executor: Executor,
    *,
    archive: str | None = None,
    calibration_id: str = LOGGED_CALIBRATION,
    kinematics: dict[str, Any] | None = None,
    software_version: str | None = None,
    progress: Callable[[Summary], None] | None = None,
) -> Summary:
    """Re-fit ``measurements`` with ``executor`` and store each new result as a version."""
    from lrms import __version__

    t0 = time.monotonic()
    sw = software_version or __version__
    items = list(measurements)
    by_id = {m.measurement_id: m for m in items}
    done = store.done_hashes(list(by_id), calibration_id, sw)
    tasks = [
        Task(
            measurement_id=m.measurement_id,
            url=log_url(archive, m.raw_path),
            software_version=sw,
            calibration_id=calibration_id,
            kinematics=kinematics,
            done_hashes=frozenset(done.get(m.measurement_id, ())),
            part=m.part,
            recipe=m.recipe,
            recipe_version=m.recipe_version,
        )
        for m in items
    ]
    summary = Summary(total=len(tasks), calibration_id=calibration_id, software_version=sw)
    if progress is not None:
        progress(summary)
    for out in executor(tasks):
        summary.cpu_s += out.cpu_s
        if out.status == "done" and out.result is not None and out.raw_sha256 is not None:
            try:
                number: int | None = store.add(out.measurement_id, out.raw_sha256, calibration_id, sw, out.result)
            except VersionStoreError as exc:  # this result cannot be stored: its task failed, the run goes on
                summary.failed.append({"measurement_id": out.measurement_id, "reason": str(exc)})
                if progress is not None:
                    progress(summary)
                continue
            if number is None:
                summary.skipped += 1
            else:
                summary.done += 1
                _compare(summary, by_id[out.measurement_id], out.result, number)
        elif out.status == "skipped":
            summary.skipped += 1
        else:
            summary.failed.append({"measurement_id": out.measurement_id, "reason": out.reason})
        if progress is not None:
            progress(summary)
    summary.wall_s = time.monotonic() - t0
    return summary


def _compare(summary: Summary, m: Archived, new: dict[str, Any], version: int) -> None:
    d0 = m.original_diameter_m
    d1, u1 = diameter_and_u(new)
    if d0 is not None and d1 is not None and u1 is not None and abs(d1 - d0) > u1:
        summary.diameter_changes.append(
            {"measurement_id": m.measurement_id, "version": version, "original_m": d0, "new_m": d1, "u_m": u1}
        )
    c0, c1 = m.original_decision, decision_of(new)
    if c0 != c1 and (c0 is not None or c1 is not None):
        summary.decision_changes.append(
            {"measurement_id": m.measurement_id, "version": version, "original": c0, "new": c1}
        )


def write_parquet(path: str | Path, store: VersionStore, measurements: Iterable[Archived]) -> int:
    """One row per stored result version of ``measurements`` (the columns: docs/fleet.md) to a
    Parquet file; returns the number of rows."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    by_id = {m.measurement_id: m for m in measurements}
    versions = store.versions(list(by_id))
    cols: dict[str, list[Any]] = {
        k: []
        for k in (
            "measurement_id",
            "version",
            "created_at",
            "software_version",
            "calibration_id",
            "raw_sha256",
            "diameter_m",
            "expanded_u_m",
            "decision",
            "diameter_range_excess_m",
            "original_diameter_m",
            "original_decision",
            "result_json",
        )
    }
    for v in versions:
        m = by_id[v.measurement_id]
        d, u = diameter_and_u(v.result)
        cols["measurement_id"].append(v.measurement_id)
        cols["version"].append(v.version)
        cols["created_at"].append(dt.datetime.fromtimestamp(v.created_at, tz=dt.UTC))
        cols["software_version"].append(v.software_version)
        cols["calibration_id"].append(v.calibration_id)
        cols["raw_sha256"].append(v.raw_sha256)
        cols["diameter_m"].append(d)
        cols["expanded_u_m"].append(u)
        cols["decision"].append(decision_of(v.result))
        # a cylinder fit outside its request's nominal range within 3 u (else None): its flag
        cols["diameter_range_excess_m"].append((v.result or {}).get("diameter_range_excess_m"))
        cols["original_diameter_m"].append(m.original_diameter_m)
        cols["original_decision"].append(m.original_decision)
        cols["result_json"].append(json.dumps(v.result))
    schema = pa.schema(
        [
            ("measurement_id", pa.string()),
            ("version", pa.int32()),
            ("created_at", pa.timestamp("us", tz="UTC")),
            ("software_version", pa.string()),
            ("calibration_id", pa.string()),
            ("raw_sha256", pa.string()),
            ("diameter_m", pa.float64()),
            ("expanded_u_m", pa.float64()),
            ("decision", pa.string()),
            ("diameter_range_excess_m", pa.float64()),
            ("original_diameter_m", pa.float64()),
            ("original_decision", pa.string()),
            ("result_json", pa.string()),
        ]
    )
    try:
        pq.write_table(pa.table(cols, schema=schema), str(path))
    except OSError as exc:
        raise ReprocessError(f"cannot write {path}: {exc}") from None
    return len(versions)


@dataclass(frozen=True)
class ChosenCalibration:
    """``--calibration``, resolved: its id (as result versions record it), the ``[kinematics]`` keys
    that replace the logged ones (every term of its rig model), the rig it belongs to (None: not
    known) and where it came from."""

    id: str
    kinematics: dict[str, Any]
    rig_id: str | None
    origin: Literal["file", "reprocess", "service"]


def resolve_calibration(ref: str, store: VersionStore) -> ChosenCalibration:
    """``--calibration``: a calibration file (a path or an fsspec URL; kept in the store under its
    id), or the id (or a prefix of it) of a calibration of the service's calibration store or of
    one ``lrms reprocess`` kept before."""
    from service.replay import kinematics_of_calibration

    if "://" in ref or Path(ref).exists():
        import fsspec

        try:
            with fsspec.open(ref, "rt", encoding="utf-8") as fh:
                cal = json.loads(fh.read())
        except (OSError, ValueError) as exc:
            raise ReprocessError(f"cannot read the calibration {ref}: {exc}") from None
        kin = kinematics_of_calibration(cal)  # refuses what is not a calibration before it is kept
        return ChosenCalibration(store.put_calibration(cal, source=ref), kin, None, "file")
    found = store.find_calibration(ref)
    return ChosenCalibration(found.id, kinematics_of_calibration(found.calibration), found.rig_id, found.origin)


def load_calibration(ref: str, store: VersionStore) -> tuple[str, dict[str, Any]]:
    """:func:`resolve_calibration`'s id and ``[kinematics]`` keys."""
    chosen = resolve_calibration(ref, store)
    return chosen.id, chosen.kinematics
