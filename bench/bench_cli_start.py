"""Command-line start: ``lrms fit`` / ``lrms measure`` against ``python -c pass``, and the point readers.

Run: ``.venv/bin/python -m bench.bench_cli_start [--reps 5] [--baseline-tree DIR]``. Part 1 starts
each command as a fresh process (``sys.executable -m service.cli.main ...``, the way the tests
do), interleaved ``--reps`` times, and prints the least wall time and the least CPU time (user +
system, from the process's own rusage: on a shared machine the CPU time moves less than the wall
time) with their ratio to ``python -c pass`` measured in the same run. "fit imports" is the
import work ``lrms fit FILE`` does for a cylinder (the modules its ``run`` imports; with pykdtree
installed the default fit imports nothing of scipy: the normals' k-d tree is pykdtree's, about
1 ms to import against 0.3 s for scipy.spatial's cKDTree, the fallback; nearest sampled points on
grids, the plane's piece test in numpy, the footprint model and its scipy.special on first use);
"fit 2k-point cloud" is the whole command on a 2,000-point cylinder (``--no-line-of-sight``).
"measure: until the sweep starts"
runs ``lrms measure`` on the default simulated rig (at 45 deg/s, so the run is short) and
takes the time from starting the process to the raw log's measurement record, which the rig
process writes just before it enables the drive and commands the approach move
(``service.rig.Rig._measure``, then ``service.sweep.run_sweep``); its CPU column is the CPU time
of the whole run (sweep and fit included) of the command and the processes waited for below it
(the rig process and the simulated rig; the kernel adds a waited-for child's time to its
parent's ``wait4`` usage; the fit worker counts only if reaped before the rig process exits), so
its difference between two trees is mostly start-up work. Below the
table, "first motion" is the time from starting the process to the first motor sample of the raw
log (its host sample time) whose shaft angle differs from the log's first sample by more than
1e-4 rad (0.006 deg): the drive enabled and the approach move under way, as the driver read it
back over the bus. "measure --server: until the sweep
starts" is the same time for ``lrms measure --server URL`` against an ``lrms serve`` of this tree
that the bench starts once on 127.0.0.1 (the rig already up; the raw log fetched with ``--out``);
its CPU column is the client process's own. With ``--baseline-tree`` (another
checkout, e.g. ``git worktree add /tmp/startbase e86473c``) the lrms rows run on that tree too,
interleaved, and the ratio baseline / this tree is printed.
Part 2 reads 100,000-point clouds (.xyz, .csv with a header, ASCII and binary .ply) with
:func:`service.pointio.read_points` and, as the baseline in the same run, with the readers it
replaces (the line-by-line text parser, :mod:`plyfile` for every PLY).
Goal (issue 15): ``lrms fit`` and ``lrms measure`` start in <= 0.3 s.
"""

from __future__ import annotations

import argparse
import contextlib
import math
import os
import secrets
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
FIT_IMPORTS = (
    "import service.cli.main, service.cli.fit, service.pointio, service.fitting, lrms.kinematics, "
    "lrms.budget, lrms.covariance, lrms.cylinder, lrms.uncertainty"
)
MEASURE_ARGS = ["measure", "--target", "cylinder", "--quiet", "--speed", "45"]
#: What ``lrms measure`` imports before it starts the rig process; the other "measure:" rows are
#: the imports of the service (on a thread of the command), of the rig process, and the simulated
#: rig's imports and set-up (scene, servers bound, closed again): its parts, each a process.
MEASURE_FIRST = (
    "import contextlib, service.cli.main, service.cli.measure, service.config, service.models, service.rigproc\n"
    "with contextlib.suppress(ImportError): import service.isolated  # isolated_service (older trees: in rigproc)"
)
SIM_BUILD = "import sim.rig, sim.drive.socketcand; sim.rig.SimulatedRig().close()"
#: Seconds from starting the command to the first motion in its raw log, per case name (filled by
#: the measure cases: :func:`_sweep_start`).
MOTION: dict[str, list[float]] = {}
MOVED_RAD = 1e-4


def _env(tree: Path) -> dict[str, str]:
    return dict(os.environ, OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1", MKL_NUM_THREADS="1", PYTHONPATH=str(tree))


def _run(cmd: list[str], tree: Path = REPO) -> tuple[float, float]:
    """Wall and CPU (user + system) seconds of one process."""
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, cwd=tree, env=_env(tree), stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    _, status, usage = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - t0
    proc.returncode = os.waitstatus_to_exitcode(status)
    err = proc.stderr.read().decode() if proc.stderr else ""
    if proc.returncode != 0:
        raise SystemExit(f"{' '.join(cmd)} failed ({proc.returncode}): {err[-500:]}")
    return wall, usage.ru_utime + usage.ru_stime


def _measure_start(tree: Path, tmp: Path, name: str) -> tuple[float, float]:
    """Seconds from starting ``lrms measure`` to its raw log's measurement record (the sweep's
    start) and the CPU seconds of the whole run, all processes. The first motion goes to
    :data:`MOTION` under ``name``."""
    out = tmp / "measure.mcap"
    cmd = [sys.executable, "-m", "service.cli.main", *MEASURE_ARGS, "--data", str(tmp / "data"), "--out", str(out)]
    out.unlink(missing_ok=True)
    t0 = time.time_ns()
    proc = subprocess.Popen(cmd, cwd=tree, env=_env(tree), stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    _, _, usage = os.wait4(proc.pid, 0)  # its waited-for children (rig process, simulated rig) included
    err = proc.stderr.read().decode() if proc.stderr else ""
    if not out.exists():  # a failed measurement still copies its raw log (the start is in it)
        raise SystemExit(f"lrms measure on {tree} failed: {err[-800:]}")
    return _sweep_start(out, t0, name), usage.ru_utime + usage.ru_stime


def _sweep_start(out: Path, t0_ns: int, name: str) -> float:
    """Seconds from ``t0_ns`` (``time.time_ns``) to the measurement record of the raw log ``out``;
    the seconds to its first motion (:data:`MOVED_RAD`) are appended to ``MOTION[name]``."""
    from service.mcaplog import TOPIC_MEASUREMENT, TOPIC_MOTOR, read_log

    msgs, _ = read_log(out)
    motor = [(m.log_time_ns, m.decode().joints[0].position) for m in msgs if m.topic == TOPIC_MOTOR]
    moved = next((t for t, p in motor if abs(p - motor[0][1]) > MOVED_RAD), None) if motor else None
    if moved is None:
        raise SystemExit(f"{out}: the motor never moved")
    MOTION.setdefault(name, []).append((moved - t0_ns) / 1e9)
    return (next(m.log_time_ns for m in msgs if m.topic == TOPIC_MEASUREMENT) - t0_ns) / 1e9


@contextlib.contextmanager
def _serve(tmp: Path, token: str) -> Iterator[str]:
    """``lrms serve`` of this tree on a free 127.0.0.1 port (default simulated rig): its URL once the
    scanner is connected."""
    import json
    import urllib.request

    from service.cli.serve import LISTENING

    env = dict(_env(REPO), LRMS_OPERATOR_TOKEN=token)
    cmd = [sys.executable, "-m", "service.cli.main", "serve", "--port", "0", "--data", str(tmp / "serve")]
    proc = subprocess.Popen(
        [*cmd, "--log-level", "warning"],
        cwd=REPO,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL,
        text=True,
    )
    try:
        assert proc.stdout is not None
        url = next((line[len(LISTENING) :].strip() for line in proc.stdout if line.startswith(LISTENING)), None)
        if url is None:
            raise SystemExit(f"lrms serve exited ({proc.wait()}) without listening")
        end = time.monotonic() + 60
        while True:
            with contextlib.suppress(OSError, ValueError), urllib.request.urlopen(f"{url}/api/v1/rig", timeout=10) as r:
                if json.load(r)["scanner"]["connected"]:
                    break
            if proc.poll() is not None or time.monotonic() > end:
                raise SystemExit("lrms serve did not come up")
            time.sleep(0.2)
        yield url
    finally:
        proc.terminate()
        proc.wait(30)


def _measure_server_start(url: str, token: str, tmp: Path, name: str) -> tuple[float, float]:
    """Seconds from starting ``lrms measure --server URL`` to the raw log's measurement record,
    and the client process's CPU seconds. A failed run stops the bench with the command's error
    (the simulated rig allows 2 s of heartbeat silence since 164b9d7; a drive fault is no longer
    reset and retried, it would show here)."""
    out = tmp / "measure-server.mcap"
    cmd = [sys.executable, "-m", "service.cli.main", *MEASURE_ARGS, "--server", url, "--out", str(out)]
    env = dict(_env(REPO), LRMS_OPERATOR_TOKEN=token)
    out.unlink(missing_ok=True)
    t0 = time.time_ns()
    proc = subprocess.Popen(cmd, cwd=REPO, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    _, status, usage = os.wait4(proc.pid, 0)
    err = proc.stderr.read() if proc.stderr else ""
    if os.waitstatus_to_exitcode(status) == 0 and out.exists():
        return _sweep_start(out, t0, name), usage.ru_utime + usage.ru_stime
    raise SystemExit(f"lrms measure --server {url} failed: {err[-500:]}")


def _cylinder_file(path: Path, n: int) -> None:
    rng = np.random.default_rng(0)
    t = rng.uniform(-1.0, 1.0, n)
    z = rng.uniform(-0.3, 0.3, n)
    pts = np.column_stack([2.5 - 0.138 * np.cos(t), 0.138 * np.sin(t), z]) + rng.normal(0, 5e-4, (n, 3))
    np.savetxt(path, pts, fmt="%.7f")


Case = tuple[str, Callable[[Path], tuple[float, float]], bool]


def start_times(reps: int, tmp: Path, baseline: Path | None) -> None:
    token = secrets.token_hex(8)
    with _serve(tmp, token) as url:
        _start_times(reps, tmp, baseline, url, token)


def _start_times(reps: int, tmp: Path, baseline: Path | None, url: str, token: str) -> None:
    small = tmp / "small.xyz"
    _cylinder_file(small, 2000)
    py = sys.executable
    lrms = [py, "-m", "service.cli.main"]

    def _tag(tree: Path, what: str) -> str:
        return what if tree == REPO else f"base: {what}"

    def cmd(argv: list[str]) -> Callable[[Path], tuple[float, float]]:
        return lambda tree: _run(argv, tree)

    cases: list[Case] = [  # (name, run on a tree, also on the baseline tree)
        ("python -c pass (baseline)", cmd([py, "-c", "pass"]), False),
        ("python -c 'import numpy'", cmd([py, "-c", "import numpy"]), False),
        ("python -c 'import scipy.optimize'", cmd([py, "-c", "import scipy.optimize"]), False),
        ("python -c 'import scipy.spatial'", cmd([py, "-c", "import scipy.spatial"]), False),
        ("lrms --help", cmd([*lrms, "--help"]), True),
        ("lrms fit --help", cmd([*lrms, "fit", "--help"]), True),
        ("lrms measure --help", cmd([*lrms, "measure", "--help"]), True),
        ("lrms fit imports", cmd([py, "-c", FIT_IMPORTS]), True),
        ("measure: command before the rig process", cmd([py, "-c", MEASURE_FIRST]), True),
        ("measure: service imports (API thread)", cmd([py, "-c", "import service.api.core"]), True),
        ("measure: rig process imports", cmd([py, "-c", "import service.rigproc, service.config, service.rig"]), True),
        ("measure: simulated rig imports + build", cmd([py, "-c", SIM_BUILD]), True),
        ("lrms fit 2k-point cloud", cmd([*lrms, "fit", str(small), "--no-line-of-sight", "--json"]), True),
        ("lrms measure: until the sweep starts", lambda tree: _measure_start(tree, tmp, _tag(tree, "embedded")), True),
        (
            "lrms measure --server: until the sweep starts",
            lambda tree: _measure_server_start(url, token, tmp, "server"),
            False,
        ),
    ]
    trees = [("", REPO)] + ([("base: ", baseline)] if baseline is not None else [])
    rows = [(tag + name, fn, tree) for name, fn, both in cases for tag, tree in trees if both or not tag]
    walls: dict[str, list[float]] = {name: [] for name, _, _ in rows}
    cpus: dict[str, list[float]] = {name: [] for name, _, _ in rows}
    for _name, fn, tree in rows:  # warm the file cache
        fn(tree)
    for _ in range(reps):
        for name, fn, tree in rows:
            w, c = fn(tree)
            walls[name].append(w)
            cpus[name].append(c)
    base_w, base_c = min(walls[rows[0][0]]), min(cpus[rows[0][0]])
    print(f"{'command':<46} {'wall s':>7} {'x base':>7} {'cpu s':>7} {'x base':>7}")
    for name, _, _ in rows:
        w, c = min(walls[name]), min(cpus[name])
        cpu = f"{c:>7.3f} {c / base_c:>7.1f}" if math.isfinite(c) else f"{'-':>7} {'-':>7}"
        print(f"{name:<46} {w:>7.3f} {w / base_w:>7.1f} {cpu}")
    # the warm-up run of each case is not counted
    motion = {k: v[1:] for k, v in MOTION.items()}
    print(
        "first motion (s from the command's start; least of the runs, x python -c pass): "
        + "; ".join(f"{k} {min(v):.3f} ({min(v) / base_w:.1f}x)" for k, v in motion.items() if v)
    )
    if baseline is not None:
        ratios = [f"{name}: {min(walls['base: ' + name]) / min(walls[name]):.2f}x" for name, _, both in cases if both]
        print("baseline tree / this tree (wall): " + "; ".join(ratios))
    print(f"(least of {reps} interleaved runs; goal: lrms fit / measure start <= 0.3 s)")


def _best(fn: Callable[[], object], reps: int) -> float:
    fn()
    times = []
    for _ in range(reps):
        t0 = time.process_time()
        fn()
        times.append(time.process_time() - t0)
    return min(times)


def reader_times(reps: int, tmp: Path) -> None:
    from plyfile import PlyData, PlyElement

    from service.pointio import _parse_text_lines, read_points

    rng = np.random.default_rng(1)
    pts = rng.uniform(-3.0, 3.0, (100_000, 3))
    xyz, csv, ply_a, ply_b = tmp / "c.xyz", tmp / "c.csv", tmp / "c_ascii.ply", tmp / "c.ply"
    np.savetxt(xyz, pts, fmt="%.7f")
    np.savetxt(csv, pts, fmt="%.7f", delimiter=",", header="x,y,z", comments="")
    v = np.empty(pts.shape[0], dtype=[("x", "f4"), ("y", "f4"), ("z", "f4")])
    v["x"], v["y"], v["z"] = pts.T
    PlyData([PlyElement.describe(v, "vertex")], text=True).write(str(ply_a))
    PlyData([PlyElement.describe(v, "vertex")]).write(str(ply_b))

    def old_text(p: Path) -> object:
        return _parse_text_lines(p, p.read_text(encoding="utf-8"))

    def old_ply(p: Path) -> object:
        vert = PlyData.read(str(p))["vertex"]
        return np.column_stack([np.asarray(vert[c], dtype=np.float64) for c in ("x", "y", "z")])

    print(f"\n{'100k points':<16} {'baseline s':>10} {'read_points s':>13} {'speed-up':>9}   baseline")
    for label, path, old, what in (
        (".xyz", xyz, old_text, "line-by-line parser"),
        (".csv + header", csv, old_text, "line-by-line parser"),
        (".ply ASCII", ply_a, old_ply, "plyfile"),
        (".ply binary", ply_b, old_ply, "plyfile"),
    ):
        new_pts = read_points(path)
        if not np.allclose(new_pts, np.asarray(old(path)), rtol=1e-6, atol=1e-6):
            raise SystemExit(f"{label}: the readers disagree")
        t_old = _best(lambda p=path, f=old: f(p), reps)  # type: ignore[misc]
        t_new = _best(lambda p=path: read_points(p), reps)  # type: ignore[misc]
        print(f"{label:<16} {t_old:>10.4f} {t_new:>13.4f} {t_old / t_new:>8.1f}x   {what}")
    print("(CPU seconds, least of the runs)")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--reps", type=int, default=5)
    ap.add_argument("--baseline-tree", type=Path, default=None, help="another checkout to time alongside")
    ap.add_argument("--skip-readers", action="store_true", help="only the start-up table")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as d:
        start_times(args.reps, Path(d), args.baseline_tree)
        if args.skip_readers:
            return
        reader_times(max(args.reps // 2, 2), Path(d))


if __name__ == "__main__":
    main()
