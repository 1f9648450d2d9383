"""Neighbourhoods on uniform grids, in numpy (no :mod:`scipy.spatial`): the detection's normals
and its nearest sampled point.

Importing :mod:`scipy.spatial` (with scipy.sparse, scipy.linalg and scipy.special) for its k-d
tree was about 0.3 s of ``lrms fit``'s start, more than the search itself; an exact k-nearest
search in numpy was ten times slower than the tree (measured, not kept). What the detection needs
is less: normals good to a few degrees for the RANSACs, and which sampled point lies next to a
point of the cloud.

:func:`grid_normals`: the points are binned into cubic cells; each cell's ten moments (count,
sums of coordinates and of their products) are summed over the 3 x 3 x 3 cells around it, and a
point's normal is the smallest-eigenvector of the covariance of its own cell's neighbourhood, on
the finest of a few doubling cell sizes at which that neighbourhood holds at least ``k`` points
and is not a line (its middle principal variance at least :data:`LINEAR_RATIO` of its largest:
a grazing table's neighbourhood of one or two scan lines fixes no normal); i.e. the scale of the
``k`` nearest neighbours, adapted to the density of the part's surface, a table's sparse scan
lines and scattered clutter.

:func:`nearest_in_grid`: each query's nearest data point among the 3 x 3 x 3 cells around its own;
where those are empty, on cells twice as large, and so on.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from lrms.cylinder.model import smallest_eigenvectors

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]

#: The 27 cell offsets of a neighbourhood.
_OFFSETS = np.array([(i, j, k) for i in (-1, 0, 1) for j in (-1, 0, 1) for k in (-1, 0, 1)], dtype=np.int64)
#: Cell sizes tried, as powers of two of the first.
LEVELS = 8
#: A neighbourhood whose middle principal variance is below this share of its largest is taken
#: as a line (one or two scan lines) and its points look on the next cell size.
LINEAR_RATIO = 0.1


def _keys(cells: NDArray[np.int64], dims: NDArray[np.int64]) -> NDArray[np.int64]:
    return np.asarray((cells[:, 0] * dims[1] + cells[:, 1]) * dims[2] + cells[:, 2], dtype=np.int64)


def _base_cell(pts: FloatArray, k: int) -> float:
    """A cell size at which a typical point's 27 cells hold about ``k`` of its neighbours: two
    thirds of the median ``k``-th neighbour distance of 32 points (brute force; the cube's side
    is then twice that distance)."""
    n = pts.shape[0]
    pick = pts[np.linspace(0, n - 1, min(32, n)).astype(np.intp)]
    d2 = np.sum(pick * pick, axis=1)[:, None] - 2.0 * pick @ pts.T + np.sum(pts * pts, axis=1)[None, :]
    kk = min(k, n) - 1
    kth = np.sqrt(np.maximum(np.partition(d2, kk, axis=1)[:, kk], 0.0))
    h = float(np.median(kth)) / 1.5
    span = float(np.max(np.ptp(pts, axis=0)))
    return h if h > 1e-9 * max(span, 1e-9) else max(span, 1e-6) / 64.0


def grid_normals(points: FloatArray, k: int = 32) -> FloatArray:
    """Unit normals ``(n, 3)`` by PCA of each point's grid neighbourhood holding at least ``k``
    points and not a line (module docstring). The cell size doubles at most ``LEVELS - 1`` times
    (to 128 times the first), and stops early once a cell exceeds the cloud's largest extent (the
    3 x 3 x 3 neighbourhood then holds the whole cloud); points still left at that last size take
    their neighbourhood's covariance whatever its count and shape (with few points there, the
    normal is not meaningful)."""
    pts = np.asarray(points, dtype=np.float64)
    n = pts.shape[0]
    rel = pts - pts.min(axis=0)
    mom = np.column_stack(
        [
            np.ones(n),
            rel,
            rel[:, 0] ** 2,
            rel[:, 0] * rel[:, 1],
            rel[:, 0] * rel[:, 2],
            rel[:, 1] ** 2,
            rel[:, 1] * rel[:, 2],
            rel[:, 2] ** 2,
        ]
    )  # (n, 10)
    out = np.empty((n, 3))
    todo = np.arange(n)
    h = _base_cell(pts, k)
    span = float(np.max(np.ptp(rel, axis=0)))
    for level in range(LEVELS):
        last = level == LEVELS - 1 or h > span
        cells = np.floor(rel / h).astype(np.int64) + 1
        dims = cells.max(axis=0) + 2
        key = _keys(cells, dims)
        ukeys, inv = np.unique(key, return_inverse=True)
        inv = inv.ravel()
        m = ukeys.size
        csum = np.column_stack([np.bincount(inv, weights=mom[:, j], minlength=m) for j in range(10)])
        # the cells the remaining points lie in, and their neighbourhoods' moments
        need, at = np.unique(inv[todo], return_inverse=True)
        nsum = np.zeros((need.size, 10))
        stride = np.array([dims[1] * dims[2], dims[2], 1], dtype=np.int64)
        for off in _OFFSETS @ stride:
            nb = ukeys[need] + off
            pos = np.minimum(np.searchsorted(ukeys, nb), m - 1)
            hit = ukeys[pos] == nb
            nsum[hit] += csum[pos[hit]]
        enough = nsum[:, 0] >= k
        if last:
            enough[:] = True
        sel = np.flatnonzero(enough)
        if sel.size:
            cov = _covariances(nsum[sel])
            if not last:
                # a neighbourhood of one or two scan lines (a grazing table's) is nearly a line:
                # its normal is any direction across it; such points take the next cell size
                ev = np.linalg.eigvalsh(cov)
                flat = ev[:, 1] >= LINEAR_RATIO * ev[:, 2]
                enough[sel[~flat]] = False
                sel, cov = sel[flat], cov[flat]
            normals = np.zeros((need.size, 3))
            normals[sel] = smallest_eigenvectors(cov)
            done = enough[at]
            out[todo[done]] = normals[at[done]]
            todo = todo[~done]
        if todo.size == 0:
            break
        h *= 2.0
    return out


def _covariances(s: FloatArray) -> FloatArray:
    """``(m, 3, 3)`` covariances from ``(m, 10)`` moment sums (count, sums, sums of products)."""
    c = s[:, 0]
    mx, my, mz = s[:, 1] / c, s[:, 2] / c, s[:, 3] / c
    cov = np.empty((s.shape[0], 3, 3))
    cov[:, 0, 0] = s[:, 4] / c - mx * mx
    cov[:, 0, 1] = cov[:, 1, 0] = s[:, 5] / c - mx * my
    cov[:, 0, 2] = cov[:, 2, 0] = s[:, 6] / c - mx * mz
    cov[:, 1, 1] = s[:, 7] / c - my * my
    cov[:, 1, 2] = cov[:, 2, 1] = s[:, 8] / c - my * mz
    cov[:, 2, 2] = s[:, 9] / c - mz * mz
    return cov


def nearest_in_grid(data: FloatArray, queries: FloatArray, cell: float) -> IntArray:
    """Index of a near ``data`` point for each query: the nearest among the 27 cells of side
    ``cell`` around the query's own (the nearest of all whenever it lies within ``cell``); where
    those cells are empty, the same with cells twice as large, and so on."""
    d = np.asarray(data, dtype=np.float64)
    q = np.asarray(queries, dtype=np.float64)
    out = np.full(q.shape[0], -1, dtype=np.intp)
    if q.shape[0] == 0 or d.shape[0] == 0:
        return out
    lo = np.minimum(d.min(axis=0), q.min(axis=0))
    span = float(np.max(np.ptp(np.vstack([d, q]), axis=0)))
    h = max(cell, 1e-9)
    todo = np.arange(q.shape[0])
    while todo.size:
        cd = np.floor((d - lo) / h).astype(np.int64) + 1
        cq = np.floor((q[todo] - lo) / h).astype(np.int64) + 1
        dims = np.maximum(cd.max(axis=0), cq.max(axis=0)) + 2
        dkey = _keys(cd, dims)
        order = np.argsort(dkey, kind="stable")
        skey = dkey[order]
        qkey = _keys(cq, dims)
        best = np.full(todo.size, np.inf)
        arg = np.full(todo.size, -1, dtype=np.intp)
        stride = np.array([dims[1] * dims[2], dims[2], 1], dtype=np.int64)
        for off in np.unique(_OFFSETS[:, :2] @ stride[:2]):  # a row of three cells at a time
            a = np.searchsorted(skey, qkey + off - 1, side="left")
            b = np.searchsorted(skey, qkey + off + 1, side="right")
            cnt = b - a
            total = int(cnt.sum())
            if total == 0:
                continue
            owner = np.repeat(np.arange(todo.size), cnt)
            rows = order[np.repeat(a - (np.cumsum(cnt) - cnt), cnt) + np.arange(total)]
            diff = d[rows] - q[todo[owner]]
            d2 = np.einsum("ij,ij->i", diff, diff)
            # per query (``owner`` ascends), the smallest: its segment's minimum and where it is
            has = np.flatnonzero(cnt)
            seg = np.minimum.reduceat(d2, (np.cumsum(cnt) - cnt)[has])
            at_min = np.flatnonzero(d2 == seg[np.searchsorted(has, owner)])
            first = at_min[np.r_[True, owner[at_min][1:] != owner[at_min][:-1]]]
            w = owner[first]
            better = d2[first] < best[w]
            best[w[better]] = d2[first][better]
            arg[w[better]] = rows[first][better]
        found = arg >= 0
        out[todo[found]] = arg[found]
        todo = todo[~found]
        if h > 2.0 * span:  # cannot happen with data present; a guard
            break
        h *= 2.0
    return out
