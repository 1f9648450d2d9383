"""The generic RANSAC loop and the plane model."""

from __future__ import annotations

import numpy as np
import pytest

from lrms.errors import FitError
from lrms.ransac import PlaneModel, ransac, trials_needed


class LineModel:
    """y = m x + c on rows (x, y): a model class defined outside the package."""

    def __init__(self) -> None:
        self.m = 0.0
        self.c = 0.0

    def estimate(self, data: np.ndarray) -> bool:
        if np.ptp(data[:, 0]) < 1e-9:
            return False
        self.m, self.c = np.polyfit(data[:, 0], data[:, 1], 1)
        return True

    def residuals(self, data: np.ndarray) -> np.ndarray:
        return np.abs(data[:, 1] - (self.m * data[:, 0] + self.c))


def test_generic_loop_with_a_foreign_model_class() -> None:
    rng = np.random.default_rng(0)
    x = rng.uniform(0, 10, 300)
    y = 2.0 * x - 1.0 + rng.normal(0, 0.05, 300)
    out = rng.uniform(0, 10, (200, 2)) * [1, 20]
    data = np.vstack([np.column_stack([x, y]), out])
    model, mask = ransac(data, LineModel, 2, 0.2, rng=rng)
    assert model.m == pytest.approx(2.0, abs=0.01) and model.c == pytest.approx(-1.0, abs=0.05)
    assert mask[:300].mean() > 0.95 and mask[300:].mean() < 0.1


def test_plane_with_outliers_and_normal_agreement() -> None:
    rng = np.random.default_rng(1)
    xy = rng.uniform(-1, 1, (500, 2))
    plane = np.column_stack([xy, 0.3 + rng.normal(0, 0.002, 500)])
    junk = rng.uniform(-1, 1, (300, 3))
    data = np.vstack([plane, junk])
    model, mask = ransac(data, PlaneModel, 3, 0.01, rng=rng)
    assert abs(model.normal[2]) == pytest.approx(1.0, abs=1e-3)
    assert model.offset * np.sign(model.normal[2]) == pytest.approx(0.3, abs=2e-3)
    assert mask[:500].mean() > 0.98
    # with normals: a point on the plane whose normal disagrees is not an inlier
    pm = PlaneModel()
    pm.normal, pm.offset = np.array([0.0, 0.0, 1.0]), 0.3
    pm.normal_weight = 0.02
    rows = np.array([[0, 0, 0.3, 0, 0, 1], [0, 0, 0.3, 1, 0, 0]], dtype=float)
    res = pm.residuals(rows)
    assert res[0] == pytest.approx(0.0) and res[1] == pytest.approx(0.02 * np.pi / 2)


def test_too_few_points_and_no_consensus() -> None:
    with pytest.raises(FitError):
        ransac(np.zeros((2, 3)), PlaneModel, 3, 0.01)
    # every sample degenerate: all points identical
    with pytest.raises(FitError):
        ransac(np.ones((50, 3)), PlaneModel, 3, 0.01, max_trials=50)
    rng = np.random.default_rng(2)
    with pytest.raises(FitError):
        ransac(rng.uniform(size=(100, 3)), PlaneModel, 3, 1e-4, min_inliers=50, max_trials=100, rng=rng)


def test_trials_needed() -> None:
    assert trials_needed(0.5, 2, 0.99) == pytest.approx(np.log(0.01) / np.log(0.75))
    assert trials_needed(0.0, 2, 0.99) == np.inf
    assert trials_needed(1.0, 3, 0.99) == 1.0


def test_batched_sample_check_scores_fewer_hypotheses_and_finds_the_same_plane() -> None:
    """The T(d,d) check of batch mode: hypotheses whose own triple is mostly off them (here: the
    normals disagree) are not scored, and the plane found is the one found without the check."""
    rng = np.random.default_rng(3)
    plane = np.column_stack([rng.uniform(-1, 1, (300, 2)), rng.normal(0.0, 0.002, 300)])
    wall = np.column_stack([rng.uniform(-1, 1, 300), np.full(300, 1.5), rng.uniform(0, 1, 300)])
    clutter = rng.uniform(-1, 1.5, (600, 3))
    pts = np.vstack([plane, wall, clutter])
    nrm = np.vstack([np.tile([0.0, 0.0, 1.0], (300, 1)), np.tile([0.0, 1.0, 0.0], (300, 1))])
    nrm = np.vstack([nrm, rng.normal(size=(600, 3))])
    data = np.hstack([pts, nrm / np.linalg.norm(nrm, axis=1, keepdims=True)])

    scored: list[int] = []

    class Counted(PlaneModel):
        normal_weight = 0.01 / np.deg2rad(30.0)

        @classmethod
        def batch_inlier_residuals(cls, params: np.ndarray, rows: np.ndarray, threshold: float) -> np.ndarray:
            if rows.shape[0] == 1200:  # the scoring, not the check of the samples
                scored.append(params.shape[0])
            return super().batch_inlier_residuals(params, rows, threshold)

    class Generic(Counted):  # the sample check from the generic (B, B * 3) scoring
        batch_sample_residuals = None  # type: ignore[assignment]

    masks = []
    for check, model in ((False, Counted), (True, Counted), (True, Generic)):
        scored.clear()
        _, mask = ransac(
            data,
            model,
            3,
            0.01,
            max_trials=400,
            min_trials=400,
            rng=np.random.default_rng(1),
            batch=50,
            verify_sample=check,
        )
        masks.append(mask)
        if check:
            assert sum(scored) < 0.2 * 400  # most random triples fail the check
        else:
            assert sum(scored) > 0.9 * 400
    assert np.array_equal(masks[0], masks[1]) and np.array_equal(masks[1], masks[2])
    assert np.count_nonzero(masks[1][:600]) >= 290 and np.count_nonzero(masks[1][600:]) < 30
