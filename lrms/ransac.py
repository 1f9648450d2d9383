"""A generic RANSAC loop and a plane model.

The loop follows the usual shape (as in scikit-image's ``measure.ransac``): a *model class*
whose instances have ``estimate(data) -> bool`` (fit to a minimal or larger sample; False when
the sample is degenerate) and ``residuals(data) -> (N,)`` (non-negative distances). The loop
draws minimal samples, keeps the hypothesis with the most inliers (ties broken by the smaller
sum of squared inlier residuals), adapts the number of trials to the inlier ratio seen so
far, and finally re-estimates on all inliers of the best hypothesis.

For large clouds the hypotheses can be *scored* on a random subset (``score_size``); the
final inlier mask is always computed on the full data.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Protocol, TypeVar

import numpy as np
from numpy.typing import NDArray

from lrms.errors import FitError

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]


class RansacModel(Protocol):
    def estimate(self, data: FloatArray) -> bool: ...

    def residuals(self, data: FloatArray) -> FloatArray: ...


M = TypeVar("M", bound=RansacModel)


def trials_needed(inlier_ratio: float, min_samples: int, stop_probability: float) -> float:
    """Trials needed to draw one all-inlier sample with ``stop_probability``."""
    if inlier_ratio <= 0:
        return math.inf
    good = inlier_ratio**min_samples
    if good >= 1.0:
        return 1.0
    return math.log(1.0 - stop_probability) / math.log(1.0 - good)


def ransac(
    data: FloatArray,
    model_class: Callable[[], M],
    min_samples: int,
    residual_threshold: float,
    *,
    max_trials: int = 1000,
    min_trials: int = 0,
    stop_probability: float = 0.99,
    min_inliers: int | None = None,
    score_size: int | None = None,
    is_model_valid: Callable[[M], bool] | None = None,
    refine: bool = True,
    rng: np.random.Generator | None = None,
) -> tuple[M, BoolArray]:
    """Robustly fit ``model_class`` to the rows of ``data``.

    Returns the best model and the boolean inlier mask over all rows of ``data``. Raises
    :class:`~lrms.errors.FitError` when there are fewer than ``min_samples`` rows or no
    hypothesis reaches ``min_inliers`` (default ``min_samples``) inliers.
    """
    x = np.asarray(data, dtype=np.float64)
    n = x.shape[0]
    if n < min_samples:
        raise FitError(f"RANSAC needs at least {min_samples} points, got {n}")
    if residual_threshold <= 0 or not np.isfinite(residual_threshold):
        raise FitError(f"residual_threshold must be > 0, got {residual_threshold}")
    g = rng if rng is not None else np.random.default_rng()
    need = min_samples if min_inliers is None else max(min_inliers, min_samples)

    score_idx: NDArray[np.intp] | None = None
    if score_size is not None and n > score_size:
        score_idx = g.choice(n, size=score_size, replace=False)
    scored = x if score_idx is None else x[score_idx]
    n_scored = scored.shape[0]

    best_model: M | None = None
    best_count = -1
    best_ssr = math.inf
    limit = float(max_trials)
    trial = 0
    while (trial < limit or trial < min_trials) and trial < max_trials:
        trial += 1
        sample = x[g.choice(n, size=min_samples, replace=False)]
        model = model_class()
        if not model.estimate(sample):
            continue
        if is_model_valid is not None and not is_model_valid(model):
            continue
        res = model.residuals(scored)
        inl = res < residual_threshold
        count = int(np.count_nonzero(inl))
        ssr = float(np.sum(np.square(res[inl])))
        if count > best_count or (count == best_count and ssr < best_ssr):
            best_model, best_count, best_ssr = model, count, ssr
            limit = min(float(max_trials), trials_needed(count / n_scored, min_samples, stop_probability))

    if best_model is None:
        raise FitError("RANSAC found no valid model (every sample was degenerate)")
    mask = best_model.residuals(x) < residual_threshold
    if int(np.count_nonzero(mask)) < need:
        raise FitError(f"RANSAC: best model has {int(np.count_nonzero(mask))} inliers, fewer than the {need} needed")
    if refine:
        final = model_class()
        if final.estimate(x[mask]) and (is_model_valid is None or is_model_valid(final)):
            mask2 = final.residuals(x) < residual_threshold
            if np.count_nonzero(mask2) >= np.count_nonzero(mask):
                return final, mask2
    return best_model, mask


class PlaneModel:
    """Plane ``n . x = d`` (unit ``n``) on rows ``(x, y, z)`` or ``(x, y, z, nx, ny, nz)``.

    ``estimate`` takes 3 points (exact) or more (total least squares through the centroid).
    ``residuals`` are the orthogonal distances; with normals in the rows, plus
    ``normal_weight`` (m per rad) times the angle between the point's normal and the plane's
    (so the front of a curved surface does not pass for a plane).
    """

    normal_weight = 0.0

    def __init__(self) -> None:
        self.normal: FloatArray = np.array([0.0, 0.0, 1.0])
        self.offset = 0.0

    def estimate(self, data: FloatArray) -> bool:
        pts = np.asarray(data, dtype=np.float64)[:, :3]
        if pts.shape[0] < 3:
            return False
        c = pts.mean(axis=0)
        if pts.shape[0] == 3:
            n = np.cross(pts[1] - pts[0], pts[2] - pts[0])
            norm = float(np.linalg.norm(n))
            scale = float(np.linalg.norm(pts[1] - pts[0]) * np.linalg.norm(pts[2] - pts[0]))
            if scale <= 0 or norm < 1e-6 * scale:
                return False
            n = n / norm
        else:
            _, s, vt = np.linalg.svd(pts - c, full_matrices=False)
            if s[1] <= 1e-9 * max(s[0], 1e-300):
                return False
            n = vt[2]
        self.normal = np.asarray(n, dtype=np.float64)
        self.offset = float(self.normal @ c)
        return True

    def residuals(self, data: FloatArray) -> FloatArray:
        d = np.asarray(data, dtype=np.float64)
        res = np.abs(d[:, :3] @ self.normal - self.offset)
        if self.normal_weight > 0 and d.shape[1] >= 6:
            cosang = np.clip(np.abs(d[:, 3:6] @ self.normal), 0.0, 1.0)
            res = res + self.normal_weight * np.arccos(cosang)
        return np.asarray(res, dtype=np.float64)
