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
from lrms.cylinder.model import KnnBackend, estimate_normals, knn_query
from lrms.errors import FitError
from tests.conftest import REPO

pytest.importorskip("pykdtree")


@pytest.mark.parametrize("k", [16, 24, 50])
def test_pykdtree_and_ckdtree_give_the_same_normals(k: int) -> None:
    """On issue 15's cloud (part, table, clutter; range noise 11.67 mm) and on a simulated rig
    sweep with clutter, the normals of both backends are bit for bit equal: the same
    neighbourhoods in the same order, so the same arithmetic."""
    for pts in (issue15_cloud(3000, seed=1), seed.lrms_sweep(np.random.default_rng(21), clutter=0.1)[0]):
        a = estimate_normals(pts, k, chunk=1000, backend="pykdtree")  # several chunks
        b = estimate_normals(pts, k, chunk=1000, backend="scipy")
        assert a.shape == b.shape == pts.shape
        np.testing.assert_array_equal(a, b)


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
    np.testing.assert_array_equal(estimate_normals(wide, backend="pykdtree"), estimate_normals(wide, backend="scipy"))


_THREADS_PROBE = """
import os, numpy as np
from bench.cylinder_clouds import issue15_cloud
from lrms.cylinder.model import estimate_normals
pts = issue15_cloud(20000, seed=0)
before = len(os.listdir("/proc/self/task"))
estimate_normals(pts, 24, backend="pykdtree")
print(before, len(os.listdir("/proc/self/task")), repr(os.environ.get("OMP_NUM_THREADS")))
"""


@pytest.mark.skipif(not os.path.isdir("/proc/self/task"), reason="counts threads in /proc")
@pytest.mark.parametrize(
    ("omp", "extra"),
    [(None, 0), ("", 0), ("2", 1)],
    ids=["unset: one thread", "empty counts as unset", "OMP_NUM_THREADS=2"],
)
def test_pykdtree_queries_run_on_the_calling_thread_unless_asked(omp: str | None, extra: int) -> None:
    """pykdtree's OpenMP would start a thread per core; without ``OMP_NUM_THREADS`` (or with it
    empty, which libgomp takes as unset) the normals start none and leave the variable as it
    was; with ``OMP_NUM_THREADS=2`` one more thread runs."""
    env = {k: v for k, v in os.environ.items() if k != "OMP_NUM_THREADS"}
    env.update(OPENBLAS_NUM_THREADS="1", PYTHONPATH=str(REPO))
    if omp is not None:
        env["OMP_NUM_THREADS"] = omp
    out = subprocess.run(
        [sys.executable, "-c", _THREADS_PROBE], capture_output=True, text=True, cwd=REPO, env=env, check=True
    )
    before, after, var = out.stdout.split()
    assert int(after) == int(before) + extra, out.stdout
    assert var == repr(omp)


BACKENDS: tuple[KnnBackend, ...] = ("pykdtree", "scipy")


@pytest.mark.parametrize("backend", BACKENDS)
def test_knn_query_always_returns_m_by_k_indices(backend: KnnBackend) -> None:
    """``(m, k)`` intp for any ``k`` from 2 to n, and for a single query row (pykdtree and cKDTree
    would squeeze ``k = 1`` to 1-D; that ``k`` is refused below)."""
    pts = issue15_cloud(200, seed=4)
    query = knn_query(pts, backend)
    for q, k in ((pts[:7], 2), (pts[:1], 5), (pts, pts.shape[0])):
        idx = query(q, k)
        assert idx.shape == (q.shape[0], k)
        assert idx.dtype == np.intp
        assert idx.min() >= 0 and idx.max() < pts.shape[0]
    np.testing.assert_array_equal(np.sort(query(pts[:3], pts.shape[0]), axis=1), np.tile(np.arange(200), (3, 1)))


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("k", [0, 1, 201, 2.0], ids=["k=0", "k=1", "k>n", "float k"])
def test_knn_query_refuses_k_outside_2_to_n(backend: KnnBackend, k: int) -> None:
    """``k > n`` would give pykdtree's sentinel 4294967295 or cKDTree's ``n`` as an index."""
    pts = issue15_cloud(200, seed=4)
    with pytest.raises(FitError, match=r"2 <= k <= n = 200"):
        knn_query(pts, backend)(pts[:4], k)


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("bad", [np.nan, np.inf])
def test_non_finite_points_are_a_fit_error_not_an_index_error(backend: KnnBackend, bad: float) -> None:
    """pykdtree used to answer a NaN point with ``IndexError: index 4294967295 is out of bounds``
    inside the normals; now the tree, its queries and the normals refuse it by name."""
    pts = issue15_cloud(300, seed=5)
    dirty = pts.copy()
    dirty[17, 1] = bad
    with pytest.raises(FitError, match="must be finite: 1 of 300 rows"):
        knn_query(dirty, backend)
    with pytest.raises(FitError, match="query points must be finite"):
        knn_query(pts, backend)(dirty[10:20], 4)
    with pytest.raises(FitError, match="must be finite"):
        estimate_normals(dirty, 16, backend=backend)


@pytest.mark.parametrize("backend", BACKENDS)
def test_query_points_must_match_the_tree_dimension(backend: KnnBackend) -> None:
    pts = issue15_cloud(100, seed=6)
    with pytest.raises(FitError, match=r"query points must be a \(n, 3\) array"):
        knn_query(pts, backend)(pts[:5, :2], 3)
    with pytest.raises(FitError, match=r"points for normals must be a \(n, 3\) array"):
        estimate_normals(pts[:, :2], backend=backend)


@pytest.mark.parametrize("name", ["pykdtre", "cKDTree", "", "Scipy"])
def test_a_misspelt_backend_is_an_error_not_auto(name: str) -> None:
    pts = issue15_cloud(100, seed=6)
    with pytest.raises(FitError, match="unknown k-nearest-neighbour backend"):
        knn_query(pts, name)  # type: ignore[arg-type]
    with pytest.raises(FitError, match="unknown k-nearest-neighbour backend"):
        estimate_normals(pts, backend=name)  # type: ignore[arg-type]
