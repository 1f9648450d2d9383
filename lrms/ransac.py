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
    batch: int = 0,
    verify_sample: bool = True,
) -> tuple[M, BoolArray]:
    """Robustly fit ``model_class`` to the rows of ``data``.

    Returns the best model and the boolean inlier mask over all rows of ``data``. Raises
    :class:`~lrms.errors.FitError` when there are fewer than ``min_samples`` rows or no
    hypothesis reaches ``min_inliers`` (default ``min_samples``) inliers.

    ``batch`` > 0 (for a model class with the :class:`BatchModel` class methods, and no
    ``is_model_valid``): hypotheses are drawn, estimated and scored ``batch`` at a time as arrays
    (samples with a repeated row count as degenerate trials); the trial count adapts after each
    batch, so up to ``batch - 1`` more trials than one at a time may run. With ``verify_sample``
    (batch mode only) a hypothesis is scored only when a strict majority of the rows of its own
    minimal sample are its inliers (within ``residual_threshold``); one that fails still counts
    as a trial. Such a hypothesis is almost never the best of its batch (a sample mostly off its
    own model was not drawn from one structure), and dropping it spares its scoring on
    ``score_size`` rows; for a plane with normals in the rows most random triples fail (their
    normals disagree with the plane). A majority, not all: the best plane's triple often holds
    one row with a poor normal (requiring all changed 4 of 10 plane RANSACs' winners, a majority
    2 of 55, on issue 15's clouds).
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
    batched = batch > 0 and is_model_valid is None and hasattr(model_class, "batch_hypotheses")
    while batched and (trial < limit or trial < min_trials) and trial < max_trials:
        b = min(batch, max_trials - trial)
        trial += b
        picks = g.integers(0, n, (b, min_samples))
        srt = np.sort(picks, axis=1)
        distinct = np.all(srt[:, 1:] != srt[:, :-1], axis=1)
        samples = x[picks]
        params, valid = model_class.batch_hypotheses(samples)  # type: ignore[attr-defined]
        valid &= distinct
        if not np.any(valid):
            continue
        params = params[valid]
        if verify_sample:
            # a hypothesis must hold most of its own sample (a T(d,d) test): the rest are not scored
            by_sample = getattr(model_class, "batch_sample_residuals", None)
            if by_sample is not None:
                own = by_sample(params, samples[valid], residual_threshold)
            else:  # all hypotheses on all samples' rows, of which the (v, s) diagonal blocks
                v = params.shape[0]
                own = _batch_scores(model_class, params, samples[valid].reshape(-1, x.shape[1]), residual_threshold)
                own = own.reshape(v, v, min_samples)[np.arange(v), np.arange(v)]
            held = own < residual_threshold
            keep = 2 * np.count_nonzero(held, axis=1) > min_samples
            if not np.any(keep):
                continue
            params = params[keep]
        counts, ssrs = _count_inliers(model_class, params, scored, residual_threshold)
        top = int(np.lexsort((ssrs, -counts))[0])
        count, ssr = int(counts[top]), float(ssrs[top])
        if count > best_count or (count == best_count and ssr < best_ssr):
            best_model = model_class.from_params(params[top])  # type: ignore[attr-defined]
            best_count, best_ssr = count, ssr
            limit = min(float(max_trials), trials_needed(count / n_scored, min_samples, stop_probability))
    while not batched and (trial < limit or trial < min_trials) and trial < max_trials:
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


def _batch_scores(model_class: object, params: FloatArray, data: FloatArray, threshold: float) -> FloatArray:
    """``(B, m)`` residuals of ``B`` hypotheses on ``data`` (``inf`` allowed above ``threshold``)."""
    if hasattr(model_class, "batch_inlier_residuals"):
        res = model_class.batch_inlier_residuals(params, data, threshold)
    else:
        res = model_class.batch_residuals(params, data)  # type: ignore[attr-defined]
    return np.asarray(res, dtype=np.float64)


#: Residuals per block of :func:`_count_inliers` (hypotheses x rows): 128 kB of float64. Larger
#: ``(B, m)`` temporaries cost several times more per entry (fresh memory from the system for every
#: array: at 50 x 1000 a plane batch's scoring took 3.4 times as long as in blocks of 16).
SCORE_BLOCK = 16_384


def _count_inliers(
    model_class: object, params: FloatArray, data: FloatArray, threshold: float
) -> tuple[NDArray[np.intp], FloatArray]:
    """Each hypothesis's inliers on ``data`` (residual below ``threshold``) and the sum of their
    squared residuals, scored in blocks of hypotheses of at most :data:`SCORE_BLOCK` residuals
    (the same numbers as in one block: each hypothesis's row is summed alone)."""
    per = max(1, SCORE_BLOCK // max(data.shape[0], 1))
    counts = np.empty(params.shape[0], dtype=np.intp)
    ssrs = np.empty(params.shape[0])
    for s in range(0, params.shape[0], per):
        res = _batch_scores(model_class, params[s : s + per], data, threshold)
        inl = res < threshold
        counts[s : s + per] = np.count_nonzero(inl, axis=1)
        ssrs[s : s + per] = np.sum(np.where(inl, res * res, 0.0), axis=1)
    return counts, ssrs


class BatchModel(Protocol):
    """Optional class methods of a model class for :func:`ransac`'s ``batch`` mode: hypotheses
    from ``(B, min_samples, d)`` samples as a ``(B, k)`` parameter array and a validity mask,
    their ``(B, m)`` residuals on ``(m, d)`` rows, and the model of one parameter row."""

    @classmethod
    def batch_hypotheses(cls, samples: FloatArray) -> tuple[FloatArray, BoolArray]: ...

    @classmethod
    def batch_residuals(cls, params: FloatArray, data: FloatArray) -> FloatArray: ...

    @classmethod
    def from_params(cls, row: FloatArray) -> RansacModel: ...


def angle_gate_cosine(threshold: float, weight: float) -> float:
    """The cosine below which a row's angle term alone (``weight`` m/rad) reaches ``threshold``:
    such a row is no inlier whatever its distance (less 1e-9, so rounding never drops one)."""
    if weight <= 0:
        return -np.inf
    return float(np.cos(min(threshold / weight, np.pi))) - 1e-9


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

    @classmethod
    def batch_hypotheses(cls, samples: FloatArray) -> tuple[FloatArray, BoolArray]:
        """Planes through ``(B, 3, d)`` point triples: rows ``(nx, ny, nz, offset)``."""
        p = samples[:, :, :3]
        d1, d2 = p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]
        # d1 x d2 and the norms by component (np.cross and np.linalg.norm cost more in call
        # overhead than in arithmetic on a batch of 50; the same operations, the same numbers)
        a0, a1, a2 = d1[:, 0], d1[:, 1], d1[:, 2]
        b0, b1, b2 = d2[:, 0], d2[:, 1], d2[:, 2]
        n = np.empty((p.shape[0], 3))
        n[:, 0] = a1 * b2 - a2 * b1
        n[:, 1] = a2 * b0 - a0 * b2
        n[:, 2] = a0 * b1 - a1 * b0
        norm = np.sqrt(n[:, 0] * n[:, 0] + n[:, 1] * n[:, 1] + n[:, 2] * n[:, 2])
        scale = np.sqrt(a0 * a0 + a1 * a1 + a2 * a2) * np.sqrt(b0 * b0 + b1 * b1 + b2 * b2)
        ok = (scale > 0) & (norm >= 1e-6 * scale)
        n /= np.where(ok, norm, 1.0)[:, None]
        offset = np.einsum("bi,bi->b", n, p.mean(axis=1))
        return np.column_stack([n, offset]), ok

    @classmethod
    def batch_residuals(cls, params: FloatArray, data: FloatArray) -> FloatArray:
        d = np.asarray(data, dtype=np.float64)
        res = np.abs(params[:, :3] @ d[:, :3].T - params[:, 3:4])
        if cls.normal_weight > 0 and d.shape[1] >= 6:
            cosang = np.minimum(np.abs(params[:, :3] @ d[:, 3:6].T), 1.0)
            res += cls.normal_weight * np.arccos(cosang)
        return np.asarray(res, dtype=np.float64)

    @classmethod
    def batch_inlier_residuals(cls, params: FloatArray, data: FloatArray, threshold: float) -> FloatArray:
        """:meth:`batch_residuals` where they can be below ``threshold``, ``inf`` elsewhere (the
        angle term, an arccos, is only taken for rows whose distance alone is below it)."""
        d = np.asarray(data, dtype=np.float64)
        res = np.abs(params[:, :3] @ d[:, :3].T - params[:, 3:4])
        if cls.normal_weight > 0 and d.shape[1] >= 6:
            # all cosines by one (B, 3) x (3, m) product; the arccos only where it can matter:
            # the distance below the threshold and the angle below threshold / weight
            cos = np.abs(params[:, :3] @ d[:, 3:6].T)
            near = (res < threshold) & (cos > angle_gate_cosine(threshold, cls.normal_weight))
            out = np.full(res.shape, np.inf)
            out[near] = res[near] + cls.normal_weight * np.arccos(np.minimum(cos[near], 1.0))
            return out
        return np.asarray(res, dtype=np.float64)

    @classmethod
    def batch_sample_residuals(cls, params: FloatArray, samples: FloatArray, threshold: float) -> FloatArray:
        """The residuals ``(B, s)`` of each of ``B`` planes on the rows of its own sample
        ``(B, s, d)`` (for :func:`ransac`'s sample check; ``inf`` where above ``threshold``)."""
        n = params[:, None, :3]
        res = np.abs(np.sum(samples[:, :, :3] * n, axis=2) - params[:, 3:4])
        if cls.normal_weight > 0 and samples.shape[2] >= 6:
            cos = np.minimum(np.abs(np.sum(samples[:, :, 3:6] * n, axis=2)), 1.0)
            res = res + cls.normal_weight * np.arccos(cos)
        return np.asarray(np.where(res < threshold, res, np.inf), dtype=np.float64)

    @classmethod
    def from_params(cls, row: FloatArray) -> PlaneModel:
        model = cls()
        model.normal = np.asarray(row[:3], dtype=np.float64).copy()
        model.offset = float(row[3])
        return model
