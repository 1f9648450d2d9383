"""Gauss-Helmert fits and automatic initial values on the simulated joints of Table 1."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from lrms.elbow import fit_auto, fit_elbow, initial_values
from lrms.elbow.model import ElbowParams, rotation_matrix
from sim.scene.joints import TABLE1, make_joint, random_pose

SHARP = {"c", "f"}  # A = 0.5 D


def _angle_deg(r1: np.ndarray, r2: np.ndarray) -> float:
    return math.degrees(float(np.linalg.norm(Rotation.from_matrix(r1 @ r2.T).as_rotvec())))


def _perturbed(t: ElbowParams) -> ElbowParams:
    return replace(
        t,
        center=t.center + 0.003,
        rot=rotation_matrix(0.02, 0.01, -0.02) @ t.rot,
        A=t.A * 1.05,
        D=t.D * 0.97,
        Df=None if t.Df is None else t.Df * 1.03,
    )


@pytest.mark.parametrize("name", list(TABLE1))
def test_noise_free_fit_is_exact(name: str) -> None:
    rng = np.random.default_rng(3)
    c, rot = random_pose(rng)
    j = make_joint(name, center=c, rot=rot, n_along=60, step_deg=4.0)
    fit = fit_elbow(j.points, _perturbed(j.truth))
    p, t = fit.params, j.truth
    assert fit.converged
    np.testing.assert_allclose(p.center, t.center, atol=1e-9)
    assert _angle_deg(p.rot, t.rot) < 1e-7
    assert pytest.approx(t.A, abs=1e-9) == p.A
    assert pytest.approx(t.D, abs=1e-9) == p.D
    if t.Df is not None:
        assert p.Df == pytest.approx(t.Df, abs=1e-9)
    assert fit.rmse < 1e-9


@pytest.mark.parametrize("name", list(TABLE1))
def test_noisy_fit_recovers_truth_within_its_precision(name: str) -> None:
    """1 mm Gaussian noise, 360 deg: errors within 5 sigma of the fit's own standard deviations
    (sharp joints: within 2 mm, see docs/elbow-model.md on their small bias); sigma0 = the noise."""
    rng = np.random.default_rng(11)
    c, rot = random_pose(rng)
    j = make_joint(name, center=c, rot=rot, noise=0.001, step_deg=2.0, rng=rng)
    fit = fit_elbow(j.points, _perturbed(j.truth))
    p, t, sg = fit.params, j.truth, fit.sigmas
    assert fit.sigma0 == pytest.approx(0.001, rel=0.03)
    err = np.array([*(p.center - t.center), p.A - t.A, p.D - t.D])
    sig = np.array([sg["Xc_m"], sg["Yc_m"], sg["Zc_m"], sg["A_m"], sg["D_m"]])
    if name in SHARP:
        assert np.all(np.abs(err) < 0.002)
    else:
        assert np.all(np.abs(err) < 5 * sig), (err, sig)
    assert _angle_deg(p.rot, t.rot) < 0.3
    assert 2 <= fit.iterations <= 20


def test_fixed_ratio_and_point_covariance() -> None:
    rng = np.random.default_rng(4)
    j = make_joint("b", noise=0.002, step_deg=3.0, rng=rng)
    fit = fit_elbow(j.points, _perturbed(j.truth), ratio=1.5)
    assert pytest.approx(1.5 * fit.params.D) == fit.params.A
    assert "A" not in fit.names and len(fit.names) == 7
    # with the true per-point covariance the variance factor is about 1
    n = j.points.shape[0]
    fit_w = fit_elbow(j.points, _perturbed(j.truth), cov=np.full(n, 0.002**2))
    assert fit_w.sigma0 == pytest.approx(1.0, rel=0.05)
    np.testing.assert_allclose(fit_w.params.center, fit.params.center, atol=2e-4)
    # full 3x3 covariances, anisotropic: a point with huge variance along its normal barely counts
    cov3 = np.repeat((np.eye(3) * 0.002**2)[None], n, axis=0)
    fit3 = fit_elbow(j.points, _perturbed(j.truth), cov=cov3)
    assert fit3.sigma0 == pytest.approx(fit_w.sigma0, rel=1e-6)


def test_sigmas_agree_with_scatter_over_repetitions() -> None:
    """The cofactor-matrix standard deviation of D and Xc matches the spread of repeated fits."""
    errs = []
    sig = []
    for seed in range(12):
        rng = np.random.default_rng(100 + seed)
        j = make_joint("a", noise=0.002, n_along=60, step_deg=4.0, rng=rng)
        fit = fit_elbow(j.points, j.truth)
        errs.append([fit.params.D - j.truth.D, fit.params.center[0]])
        sig.append([fit.sigmas["D_m"], fit.sigmas["Xc_m"]])
    spread = np.std(np.array(errs), axis=0, ddof=1)
    mean_sig = np.mean(np.array(sig), axis=0)
    # 12 samples: the sample std is within a factor 1.8 of the true one with high probability
    assert np.all(spread / mean_sig < 1.8) and np.all(spread / mean_sig > 1 / 1.8), (spread, mean_sig)


@pytest.mark.parametrize("name", list(TABLE1))
def test_automatic_initial_values_in_random_poses_with_half_coverage(name: str) -> None:
    spec = TABLE1[name]
    rng = np.random.default_rng(21 + ord(name))
    for view in (60.0, 150.0):
        c, rot = random_pose(rng)
        j = make_joint(name, center=c, rot=rot, coverage_deg=180.0, view_deg=view, noise=0.001, step_deg=3.0, rng=rng)
        fit = fit_auto(j.points, flange=spec.flange, rng=np.random.default_rng(0))  # degree from the cloud
        assert math.degrees(fit.params.degree) == pytest.approx(spec.degree_deg)
        t = j.truth
        ang = min(_angle_deg(fit.params.rot, t.rot), _angle_deg(fit.params.flipped().rot, t.rot))
        assert ang < 0.5
        assert np.linalg.norm(fit.params.center - t.center) < 0.003
        assert pytest.approx(t.D, abs=0.001) == fit.params.D
        assert pytest.approx(t.A, abs=0.003) == fit.params.A
        if not spec.flange:  # flanged joints have equal legs: either labelling is right
            # the longer leg (the simulation's start leg) is labelled the start leg
            assert _angle_deg(fit.params.rot, t.rot) < 0.5


def test_estimated_degree_other_than_45_or_90() -> None:
    from sim.scene.joints import JointSpec

    spec = JointSpec("x", 60.0, 1.0, False)
    j = make_joint(spec, coverage_deg=200.0, noise=0.0005, step_deg=2.0, rng=np.random.default_rng(2))
    init = initial_values(j.points)
    assert math.degrees(init.degree) == pytest.approx(60.0, abs=3.0)
    fit = fit_auto(j.points, degree=math.radians(60.0))
    assert np.linalg.norm(fit.params.center - j.truth.center) < 0.002
