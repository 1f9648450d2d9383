"""Mounting-bracket detection on a fitted elbow (seed 000, Section 2.3.2).

1. Fit the elbow (trimmed, so the bracket itself does not pull the fit) or take a given fit.
2. Points whose distance to the fitted surface exceeds a threshold (default ``K_SIGMA`` times the
   fit's sigma0, at least ``MIN_THRESHOLD_D`` of D) are candidates.
3. The candidates are grouped by DBSCAN (:func:`dbscan`, on a scipy ``cKDTree``); the largest
   group is the bracket.
4. A RANSAC cylinder (:class:`lrms.cylinder.CylinderModel` in :func:`lrms.ransac.ransac`, two
   points with normals per hypothesis) on the largest group gives the bracket's support rod and
   refines its points.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from lrms.cylinder import Cylinder, CylinderModel, estimate_normals, refine_cylinder
from lrms.elbow.gauss_helmert import ElbowFit
from lrms.elbow.model import as_points, condition
from lrms.elbow.pipeline import fit_auto
from lrms.errors import FitError
from lrms.ransac import ransac

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]

K_SIGMA = 4.0
MIN_THRESHOLD_D = 0.02
#: DBSCAN radius in units of the cloud's median point spacing.
EPS_SPACING = 3.0
MIN_SAMPLES = 8


def dbscan(points: ArrayLike, eps: float, min_samples: int) -> NDArray[np.int64]:
    """DBSCAN cluster labels (0, 1, ... by decreasing size; -1 for noise), vectorized.

    Core points have at least ``min_samples`` points (themselves included) within ``eps``;
    clusters are the connected components of core points linked within ``eps``; a border point
    joins the cluster of a core point within ``eps`` of it.
    """
    pts = np.asarray(points, dtype=np.float64)
    n = pts.shape[0]
    if eps <= 0 or min_samples < 1:
        raise FitError("DBSCAN needs eps > 0 and min_samples >= 1")
    labels = np.full(n, -1, dtype=np.int64)
    if n == 0:
        return labels
    pairs = cKDTree(pts).query_pairs(eps, output_type="ndarray")
    i, j = (pairs[:, 0], pairs[:, 1]) if pairs.size else (np.zeros(0, np.intp), np.zeros(0, np.intp))
    count = 1 + np.bincount(i, minlength=n) + np.bincount(j, minlength=n)
    core = count >= min_samples
    both = core[i] & core[j]
    graph = coo_matrix((np.ones(int(both.sum())), (i[both], j[both])), shape=(n, n))
    _, comp = connected_components(graph, directed=False)
    labels[core] = comp[core]
    # border points: take the component of a core neighbour
    for a, b in ((i, j), (j, i)):
        sel = core[a] & ~core[b] & (labels[b] < 0)
        labels[b[sel]] = comp[a[sel]]
    # renumber by decreasing size
    used = labels >= 0
    if used.any():
        _, inv, counts = np.unique(labels[used], return_inverse=True, return_counts=True)
        order = np.argsort(-counts, kind="stable")
        rank = np.empty_like(order)
        rank[order] = np.arange(order.size)
        labels[used] = rank[inv]
    return labels


@dataclass(frozen=True)
class BracketResult:
    """Bracket candidates and the detected bracket."""

    fit: ElbowFit
    threshold: float  # residual threshold used (m)
    candidates: IntArray  # indices of the points above the threshold
    groups: list[IntArray]  # DBSCAN groups (indices into the cloud), largest first
    centroids: list[FloatArray]  # centroid of each group (m)
    bracket: IntArray  # points of the bracket: the RANSAC cylinder's inliers in the largest group
    cylinder: Cylinder | None  # the bracket's support rod, when a cylinder was found
    length: float  # extent of the bracket points along the rod axis (m), 0 without a cylinder

    def to_dict(self) -> dict[str, object]:
        out: dict[str, object] = {
            "threshold_m": self.threshold,
            "n_candidates": int(self.candidates.size),
            "groups": [
                {"n_points": int(g.size), "centroid_m": [float(x) for x in c]}
                for g, c in zip(self.groups, self.centroids, strict=True)
            ],
            "bracket_points": int(self.bracket.size),
        }
        if self.cylinder is not None:
            out["cylinder"] = {
                "point_m": [float(x) for x in self.cylinder.point],
                "direction": [float(x) for x in self.cylinder.direction],
                "diameter_m": self.cylinder.diameter,
                "length_m": self.length,
            }
        return out


def detect_brackets(
    points: ArrayLike,
    *,
    fit: ElbowFit | None = None,
    degree: float | None = None,
    ratio: float | None = None,
    flange: bool = False,
    threshold: float | None = None,
    eps: float | None = None,
    min_samples: int = MIN_SAMPLES,
    rng: np.random.Generator | None = None,
) -> BracketResult:
    """Find mounting brackets on an elbow cloud (see the module docstring).

    Raises :class:`FitError` when the elbow cannot be fitted or no point group stands off it.
    """
    pts = as_points(points)
    g = np.random.default_rng(0) if rng is None else rng
    if fit is None:
        fit = fit_auto(pts, degree=degree, ratio=ratio, flange=flange, trim=3.5, rng=g)
    res = np.abs(condition(pts, fit.params))
    thr = threshold if threshold is not None else max(K_SIGMA * fit.sigma0, MIN_THRESHOLD_D * fit.params.D)
    cand = np.flatnonzero(res > thr)
    if cand.size < min_samples:
        raise FitError(f"no bracket: only {cand.size} points stand off the elbow by more than {thr * 1e3:.1f} mm")
    if eps is None:
        tree = cKDTree(pts)
        sample = pts[g.choice(pts.shape[0], min(pts.shape[0], 5000), replace=False)]
        d, _ = tree.query(sample, k=2)
        eps = EPS_SPACING * float(np.median(d[:, 1]))
    labels = dbscan(pts[cand], eps, min_samples)
    if not np.any(labels >= 0):
        raise FitError("no bracket: the points off the elbow form no dense group")
    groups = [cand[labels == k] for k in range(int(labels.max()) + 1)]
    largest = groups[0]
    cyl: Cylinder | None = None
    bracket = largest
    length = 0.0
    if largest.size >= 20:
        gp = pts[largest]
        normals = estimate_normals(gp, k=min(16, gp.shape[0]))
        rthr = max(3.0 * fit.sigma0, 0.01 * fit.params.D)
        try:
            model, mask = ransac(
                np.hstack([gp, normals]), CylinderModel, 2, rthr, max_trials=500, min_inliers=10, refine=False, rng=g
            )
            assert model.cylinder is not None
            cyl = model.cylinder
            if np.count_nonzero(mask) >= 10:
                cyl = refine_cylinder(gp[mask], cyl, sigma=None, max_rounds=2, gate=3.0).cylinder
                mask = np.abs(cyl.surface_distance(gp)) < rthr
            bracket = largest[mask]
            t = (pts[bracket] - cyl.point) @ cyl.direction
            length = float(t.max() - t.min()) if t.size else 0.0
        except FitError:
            cyl = None
    centroids = [np.asarray(pts[gr].mean(axis=0)) for gr in groups]
    return BracketResult(fit, float(thr), cand, groups, centroids, bracket, cyl, length)
