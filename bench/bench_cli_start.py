"""Command-line start: ``lrms fit`` / ``lrms measure`` against ``python -c pass``, and the point readers.

Run: ``.venv/bin/python -m bench.bench_cli_start [--reps 5]``. Part 1 starts each command as a
fresh process (``sys.executable -m service.cli.main ...``, the way the tests do), interleaved
``--reps`` times, and prints the least wall time and the least CPU time (user + system, from the
process's own rusage: on a shared machine the CPU time moves less than the wall time) with
their ratio to ``python -c pass`` measured in the same run. "fit imports" is the import work
``lrms fit FILE`` does before it fits (the modules its ``run`` imports for a cylinder); "fit
2k-point cloud" is the whole command on a 2,000-point cylinder (``--no-line-of-sight``).
Part 2 reads 100,000-point clouds (.xyz, .csv with a header, ASCII and binary .ply) with
:func:`service.pointio.read_points` and, as the baseline in the same run, with the readers it
replaces (the line-by-line text parser, :mod:`plyfile` for every PLY).
Goal (issue 15): ``lrms fit`` and ``lrms measure`` start in <= 0.3 s.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
FIT_IMPORTS = (
    "import service.cli.main, service.cli.fit, service.pointio, service.fitting, lrms.kinematics, "
    "lrms.budget, lrms.covariance, lrms.cylinder, lrms.uncertainty"
)


def _run(cmd: list[str]) -> tuple[float, float]:
    """Wall and CPU (user + system) seconds of one process."""
    env = dict(os.environ, OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1", MKL_NUM_THREADS="1")
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, cwd=REPO, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    _, status, usage = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - t0
    proc.returncode = os.waitstatus_to_exitcode(status)
    err = proc.stderr.read().decode() if proc.stderr else ""
    if proc.returncode != 0:
        raise SystemExit(f"{' '.join(cmd)} failed ({proc.returncode}): {err[-500:]}")
    return wall, usage.ru_utime + usage.ru_stime


def _cylinder_file(path: Path, n: int) -> None:
    rng = np.random.default_rng(0)
    t = rng.uniform(-1.0, 1.0, n)
    z = rng.uniform(-0.3, 0.3, n)
    pts = np.column_stack([2.5 - 0.138 * np.cos(t), 0.138 * np.sin(t), z]) + rng.normal(0, 5e-4, (n, 3))
    np.savetxt(path, pts, fmt="%.7f")


def start_times(reps: int, tmp: Path) -> None:
    small = tmp / "small.xyz"
    _cylinder_file(small, 2000)
    lrms = [sys.executable, "-m", "service.cli.main"]
    cases: list[tuple[str, list[str]]] = [
        ("python -c pass (baseline)", [sys.executable, "-c", "pass"]),
        ("python -c 'import numpy'", [sys.executable, "-c", "import numpy"]),
        ("python -c 'import scipy.optimize'", [sys.executable, "-c", "import scipy.optimize"]),
        ("lrms --help", [*lrms, "--help"]),
        ("lrms fit --help", [*lrms, "fit", "--help"]),
        ("lrms measure --help", [*lrms, "measure", "--help"]),
        ("lrms fit imports", [sys.executable, "-c", FIT_IMPORTS]),
        ("lrms fit 2k-point cloud", [*lrms, "fit", str(small), "--no-line-of-sight", "--json"]),
    ]
    walls: dict[str, list[float]] = {name: [] for name, _ in cases}
    cpus: dict[str, list[float]] = {name: [] for name, _ in cases}
    for _name, cmd in cases:  # warm the file cache
        _run(cmd)
    for _ in range(reps):
        for name, cmd in cases:
            w, c = _run(cmd)
            walls[name].append(w)
            cpus[name].append(c)
    base_w, base_c = min(walls[cases[0][0]]), min(cpus[cases[0][0]])
    print(f"{'command':<36} {'wall s':>7} {'x base':>7} {'cpu s':>7} {'x base':>7}")
    for name, _ in cases:
        w, c = min(walls[name]), min(cpus[name])
        print(f"{name:<36} {w:>7.3f} {w / base_w:>7.1f} {c:>7.3f} {c / base_c:>7.1f}")
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
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as d:
        start_times(args.reps, Path(d))
        reader_times(max(args.reps // 2, 2), Path(d))


if __name__ == "__main__":
    main()
