"""The normals' k-nearest-neighbour backends: pykdtree (when installed) against scipy's cKDTree."""

from __future__ import annotations

import os
import subprocess
import sys

import numpy as np
import pytest
from scipy.spatial import cKDTree

from bench import seed003_reproduction as seed
from bench.cylinder_clouds import issue15_cloud
from lrms.cylinder.model import estimate_normals, knn_query
from tests.conftest import REPO

pytest.importorskip("pykdtree")


@pytest.mark.parametrize("k", [16, 24, 50])
def test_pykdtree_and_ckdtree_give_the_same_normals(k: int) -> None:
    """On issue 15's cloud (part, table, clutter; range noise 11.67 mm) and on a simulated rig
    sweep with clutter, the normals of both backends agree to float tolerance (they are the
    same neighbourhoods, so in fact bit for bit on these clouds)."""
    for pts in (issue15_cloud(3000, seed=1), seed.lrms_sweep(np.random.default_rng(21), clutter=0.1)[0]):
        a = estimate_normals(pts, k, chunk=1000, backend="pykdtree")  # several chunks
        b = estimate_normals(pts, k, chunk=1000, backend="scipy")
        assert a.shape == b.shape == pts.shape
        np.testing.assert_allclose(a, b, rtol=0.0, atol=1e-12)


def test_knn_query_returns_the_exact_nearest_neighbours_in_order() -> None:
    pts = issue15_cloud(2000, seed=2)
    q = pts[::7] + 1e-4  # off the data points: distinct distances
    ref_d, ref_i = cKDTree(pts).query(q, k=12)
    idx = knn_query(pts, "pykdtree")(q, 12)
    np.testing.assert_array_equal(idx, ref_i)
    d = np.linalg.norm(pts[idx] - q[:, None, :], axis=-1)
    np.testing.assert_allclose(d, ref_d, rtol=1e-12)
    assert np.all(np.diff(d, axis=1) >= 0)


def test_a_non_contiguous_float32_cloud_is_searched_in_float64() -> None:
    pts = issue15_cloud(1500, seed=3)
    wide = np.asfortranarray(np.hstack([pts, pts]).astype(np.float32))[:, :3]  # strided float32 view
    np.testing.assert_allclose(
        estimate_normals(wide, backend="pykdtree"), estimate_normals(wide, backend="scipy"), rtol=0.0, atol=1e-12
    )


_THREADS_PROBE = """
import os, numpy as np
from bench.cylinder_clouds import issue15_cloud
from lrms.cylinder.model import estimate_normals
pts = issue15_cloud(20000, seed=0)
before = len(os.listdir("/proc/self/task"))
estimate_normals(pts, 24, backend="pykdtree")
print(before, len(os.listdir("/proc/self/task")), os.environ.get("OMP_NUM_THREADS", "unset"))
"""


@pytest.mark.skipif(not os.path.isdir("/proc/self/task"), reason="counts threads in /proc")
@pytest.mark.parametrize(("omp", "extra"), [(None, 0), ("2", 1)], ids=["unset: one thread", "OMP_NUM_THREADS=2"])
def test_pykdtree_queries_run_on_the_calling_thread_unless_asked(omp: str | None, extra: int) -> None:
    """pykdtree's OpenMP would start a thread per core; without ``OMP_NUM_THREADS`` the normals
    start none (and leave the variable unset), with ``OMP_NUM_THREADS=2`` one more thread runs."""
    env = {k: v for k, v in os.environ.items() if k != "OMP_NUM_THREADS"}
    env.update(OPENBLAS_NUM_THREADS="1", PYTHONPATH=str(REPO))
    if omp is not None:
        env["OMP_NUM_THREADS"] = omp
    out = subprocess.run(
        [sys.executable, "-c", _THREADS_PROBE], capture_output=True, text=True, cwd=REPO, env=env, check=True
    )
    before, after, var = out.stdout.split()
    assert int(after) == int(before) + extra, out.stdout
    assert var == (omp or "unset")
