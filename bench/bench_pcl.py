"""Benchmark: our cylinder fit against PCL 1.13's pipeline, side by side on the same clouds.

Clouds: issue 15's (``bench.cylinder_clouds``: the seed 003 part, D = 0.276 m at about 2.5 m,
standing on a table, 30 % outliers including the table, range noise 11.67 mm along the line of
sight). For each cloud, interleaved: PCL's pipeline in a small C++ harness of ours
(``bench/pcl/cylinder_pcl.cpp``: k = 50 normals, removal of the dominant plane with
SACSegmentationFromNormals, then SACSegmentationFromNormals with SACMODEL_CYLINDER; the cloud
handed over in a temporary .xyz file, the harness times its pipeline without the reading), then
``lrms.cylinder.fit_cylinder`` on the same points in this process (wall time of the call). Both
single-threaded (``OMP_NUM_THREADS=1``). Printed per size: the median time of each, the ratio
(ours / PCL; < 1: we are faster) and both tools' mean |radius error| against the true 0.138 m.

The harness is built here with g++ against Debian's ``libpcl-dev`` (flags from pkg-config; into a
cache directory under the system's temp dir, rebuilt when its source changes); without PCL the
bench says so and exits 0. PCL takes about 2-3 minutes per 1M-point cloud on this project's machine.

Run: ``.venv/bin/python -m bench.bench_pcl [--sizes 10000 100000 1000000] [--repeat N]``.
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import hashlib  # noqa: E402
import platform  # noqa: E402
import shutil  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

from bench.cylinder_clouds import issue15_cloud, truth  # noqa: E402
from lrms.cylinder import fit_cylinder  # noqa: E402
from lrms.errors import FitError  # noqa: E402

SOURCE = Path(__file__).resolve().parent / "pcl"
#: Clouds per size unless --repeat is given (PCL's 1M run takes minutes).
DEFAULT_REPEATS = {10_000: 5, 100_000: 3, 1_000_000: 1}
#: Distance threshold (m) and radius limits (m) given to PCL: those of our detection.
THRESHOLD = 0.03
RADIUS_LIMITS = (0.01, 2.0)


class PclMissing(Exception):
    """PCL (or cmake / a C++ compiler) is not installed: the bench is skipped."""


#: pkg-config modules of Debian's libpcl-dev the harness links.
PCL_MODULES = (
    "pcl_segmentation",
    "pcl_features",
    "pcl_search",
    "pcl_filters",
    "pcl_sample_consensus",
    "pcl_kdtree",
    "pcl_common",
)


def build_harness() -> Path:
    """Compile ``bench/pcl/cylinder_pcl.cpp`` with g++ against PCL (flags from pkg-config; PCL's
    own cmake package drags in VTK's MPI targets on Debian), cached by the source's hash."""
    if shutil.which("pkg-config") is None or shutil.which("g++") is None:
        raise PclMissing("pkg-config and g++ are needed to build the PCL harness")
    flags = subprocess.run(
        ["pkg-config", "--cflags", "--libs", *PCL_MODULES], capture_output=True, text=True, check=False
    )
    if flags.returncode != 0:
        raise PclMissing("PCL not found by pkg-config (Debian: apt-get install libpcl-dev)")
    version = subprocess.run(["pkg-config", "--modversion", "pcl_common"], capture_output=True, text=True, check=False)
    if not version.stdout.startswith("1.13"):
        raise PclMissing(f"PCL 1.13 is needed, pkg-config has {version.stdout.strip() or 'none'}")
    src = SOURCE / "cylinder_pcl.cpp"
    digest = hashlib.sha256(src.read_bytes() + flags.stdout.encode()).hexdigest()[:12]
    exe = Path(tempfile.gettempdir()) / f"lrms-bench-pcl-{digest}" / "cylinder_pcl"
    if exe.exists():
        return exe
    exe.parent.mkdir(parents=True, exist_ok=True)
    print("building the PCL harness (a few minutes) ...", flush=True)
    cmd = ["g++", "-O2", "-std=c++17", "-o", str(exe), str(src), *flags.stdout.split()]
    make = subprocess.run(cmd, capture_output=True, text=True, check=False)
    if make.returncode != 0 or not exe.exists():
        raise RuntimeError(f"building the PCL harness failed:\n{make.stderr[-2000:]}")
    return exe


def run_pcl(exe: Path, cloud_file: Path, seed: int) -> tuple[float, float]:
    """PCL's pipeline time (s) and fitted radius (m; nan when it found none)."""
    out = subprocess.run(
        [str(exe), str(cloud_file), str(THRESHOLD), str(RADIUS_LIMITS[0]), str(RADIUS_LIMITS[1]), str(seed)],
        capture_output=True,
        text=True,
        check=True,
        env={**os.environ, "OMP_NUM_THREADS": "1"},
    )
    fields = out.stdout.split()
    return float(fields[0]), float(fields[1])


def run_ours(pts: np.ndarray) -> tuple[float, float]:
    """Our fit's wall time (s) and radius (m; nan when it found none)."""
    t0 = time.perf_counter()
    try:
        r = fit_cylinder(pts).cylinder.radius
    except FitError:
        r = float("nan")
    return time.perf_counter() - t0, r


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", type=int, nargs="+", default=[10_000, 100_000, 1_000_000])
    ap.add_argument("--repeat", type=int, default=None, help="clouds per size (default 5 / 3 / 1)")
    args = ap.parse_args(argv)
    try:
        exe = build_harness()
    except PclMissing as exc:
        print(f"bench_pcl skipped: {exc}")
        return 0
    r_true = truth().radius
    print(f"machine: {platform.machine()} python {platform.python_version()}, 1 thread; PCL harness {exe}")
    print(
        f"{'points':>9s} {'clouds':>6s} {'PCL (s)':>9s} {'ours (s)':>9s} {'ratio':>7s} "
        f"{'PCL |dr| (mm)':>14s} {'ours |dr| (mm)':>15s}"
    )
    with tempfile.TemporaryDirectory() as tmp:
        cloud_file = Path(tmp) / "cloud.xyz"
        for n in args.sizes:
            reps = args.repeat if args.repeat is not None else DEFAULT_REPEATS.get(n, 1)
            t_pcl, t_ours, e_pcl, e_ours = [], [], [], []
            for seed in range(reps):
                pts = issue15_cloud(n, seed=seed)
                np.savetxt(cloud_file, pts, fmt="%.6f")
                # interleaved, the order alternating from cloud to cloud
                if seed % 2 == 0:
                    tp, rp = run_pcl(exe, cloud_file, seed + 1)
                    to, ro = run_ours(pts)
                else:
                    to, ro = run_ours(pts)
                    tp, rp = run_pcl(exe, cloud_file, seed + 1)
                t_pcl.append(tp)
                t_ours.append(to)
                e_pcl.append(abs(rp - r_true))
                e_ours.append(abs(ro - r_true))
            tp_med, to_med = float(np.median(t_pcl)), float(np.median(t_ours))
            print(
                f"{n:9d} {reps:6d} {tp_med:9.3f} {to_med:9.3f} {to_med / tp_med:7.3f} "
                f"{1e3 * float(np.mean(e_pcl)):14.3f} {1e3 * float(np.mean(e_ours)):15.4f}",
                flush=True,
            )
    print("ratio = ours / PCL (median times); |dr|: mean |fitted - true radius| (nan: a tool found no cylinder)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
