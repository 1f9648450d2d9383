"""Registration by one joint (Eq. 11), DBSCAN, bracket detection, and bad input."""

from __future__ import annotations

import math

import numpy as np
import pytest

from lrms.elbow import fit_auto, fit_elbow, initial_values
from lrms.elbow.brackets import dbscan, detect_brackets
from lrms.elbow.registration import register, rotation_angle_deg
from lrms.errors import FitError, LrmsError
from sim.scene.joints import add_bracket, make_joint, random_pose


def _station(rng: np.random.Generator, view: float, noise: float = 0.002):  # type: ignore[no-untyped-def]
    c, rot = random_pose(rng)
    return make_joint(
        "a", D=0.2, center=c, rot=rot, coverage_deg=180.0, view_deg=view, noise=noise, step_deg=3.0, rng=rng
    )


def test_registration_of_two_stations_matches_the_true_transform() -> None:
    rng = np.random.default_rng(8)
    j1, j2 = _station(rng, 60.0), _station(rng, 150.0)
    f1 = fit_auto(j1.points, rng=np.random.default_rng(0))
    f2 = fit_auto(j2.points, rng=np.random.default_rng(0))
    reg = register(f1, f2)
    r_true = j1.truth.rot.T @ j2.truth.rot
    t_true = j1.truth.center - r_true @ j2.truth.center
    # cloud 2 mapped into frame 1 lies on joint 1's true surface
    from lrms.elbow.model import condition

    mapped = reg.apply(j2.points)
    assert np.sqrt(np.mean(condition(mapped, j1.truth) ** 2)) < 0.003
    assert rotation_angle_deg(reg.rotation @ r_true.T) < 0.2
    at_joint = reg.apply(j2.truth.center[None])[0]
    assert np.linalg.norm(at_joint - j1.truth.center) < 0.002
    np.testing.assert_allclose(reg.matrix[:3, 3], t_true, atol=0.05)  # lever arm of metres: looser
    assert np.allclose(reg.matrix[3], [0, 0, 0, 1])
    # the error is consistent with the propagated uncertainty
    err = np.abs(at_joint - j1.truth.center)
    assert np.all(err < 6 * reg.sigma_at_joint + 1e-4)
    d = reg.to_dict()
    assert len(d["matrix"]) == 4 and d["rotation_angle_deg"] > 0  # type: ignore[arg-type]


def test_registration_covariance_matches_finite_differences() -> None:
    """The analytic Jacobian of (t, e) is checked by perturbing the fits' centres and rotations."""
    from dataclasses import replace

    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(9)
    j1, j2 = _station(rng, 60.0), _station(rng, 150.0)
    f1 = fit_elbow(j1.points, j1.truth)
    f2 = fit_elbow(j2.points, j2.truth)
    base = register(f1, f2)
    h = 1e-6
    cols = []
    for which in (1, 2):
        for k in range(6):
            d = np.zeros(6)
            d[k] = h
            fa, fb = (f1, f2) if which == 1 else (f2, f1)
            p = fa.params
            p2 = replace(p, center=p.center + d[:3], rot=Rotation.from_rotvec(-d[3:]).as_matrix() @ p.rot)
            fa2 = replace(fa, params=p2)
            reg = register(fa2, fb) if which == 1 else register(fb, fa2)
            dt = (reg.translation - base.translation) / h
            e = Rotation.from_matrix(reg.rotation @ base.rotation.T).as_rotvec() / h
            cols.append(np.concatenate([dt, e]))
    jac = np.array(cols).T
    cin = np.zeros((12, 12))
    cin[:6, :6] = f1.cov[:6, :6]
    cin[6:, 6:] = f2.cov[:6, :6]
    np.testing.assert_allclose(jac @ cin @ jac.T, base.cov, rtol=1e-3, atol=1e-14)


def test_registration_rejects_different_joints() -> None:
    rng = np.random.default_rng(10)
    a = make_joint("a", step_deg=4.0, n_along=60, rng=rng)
    b = make_joint("d", step_deg=4.0, n_along=60, rng=rng)
    with pytest.raises(FitError, match="different joints"):
        register(fit_elbow(a.points, a.truth), fit_elbow(b.points, b.truth))


def test_dbscan_groups_and_noise() -> None:
    rng = np.random.default_rng(0)
    c1 = rng.normal([0, 0, 0], 0.004, (200, 3))
    c2 = rng.normal([1, 0, 0], 0.004, (80, 3))
    lone = np.array([[5.0, 5, 5], [-5.0, 0, 0]])
    labels = dbscan(np.vstack([c1, c2, lone]), eps=0.02, min_samples=5)
    assert set(labels[:200]) == {0}
    assert set(labels[200:280]) == {1}
    assert np.all(labels[280:] == -1)
    # a chain of points spaced below eps is one cluster
    chain = np.column_stack([np.arange(50) * 0.01, np.zeros(50), np.zeros(50)])
    assert set(dbscan(chain, eps=0.015, min_samples=2)) == {0}
    with pytest.raises(FitError):
        dbscan(chain, eps=0.0, min_samples=2)


def test_bracket_is_found_on_a_simulated_joint() -> None:
    rng = np.random.default_rng(3)
    c, rot = random_pose(rng)
    j = make_joint("a", center=c, rot=rot, coverage_deg=180.0, noise=0.001, step_deg=2.0, rng=rng)
    jb = add_bracket(j, band_width=0.15, rod_length=1.0, spacing=0.02, noise=0.001, rng=rng)
    assert 0.1 < np.mean(jb.portion == 3) < 0.2
    res = detect_brackets(jb.points, rng=np.random.default_rng(0))
    truth = np.flatnonzero(jb.portion == 3)
    # the elbow fit is not pulled by the bracket
    assert np.linalg.norm(res.fit.params.center - j.truth.center) < 0.001
    assert res.fit.sigma0 < 0.0012
    # the largest group is (part of) the bracket, and the groups hold nearly all of it
    largest = res.groups[0]
    assert np.isin(largest, truth).mean() > 0.98
    assert np.isin(truth, largest).mean() > 0.5
    assert np.isin(truth, np.concatenate(res.groups)).mean() > 0.95
    # the RANSAC cylinder is the support rod: 0.3 D thick, along the bend's outward direction
    assert res.cylinder is not None
    assert res.cylinder.diameter == pytest.approx(0.03, abs=0.004)
    th = j.truth.degree / 2 + math.pi / 2
    u_world = j.truth.to_world(np.array([[math.cos(th), 0.0, math.sin(th)]]))[0] - j.truth.center
    assert abs(float(res.cylinder.direction @ u_world)) > 0.99
    assert res.length == pytest.approx(0.1, abs=0.01)


def test_no_bracket_on_a_clean_joint() -> None:
    j = make_joint("b", coverage_deg=180.0, noise=0.001, step_deg=3.0, rng=np.random.default_rng(1))
    with pytest.raises(FitError, match="no bracket"):
        detect_brackets(j.points, rng=np.random.default_rng(0))


def test_bad_input_raises_fit_errors() -> None:
    j = make_joint("a", n_along=40, step_deg=6.0)
    with pytest.raises(FitError, match="too few points"):
        fit_elbow(j.points[:10], j.truth)
    with pytest.raises(FitError, match="too few points"):
        initial_values(j.points[:50])
    with pytest.raises(FitError, match=r"shape \(n, 3\)"):
        fit_elbow(j.points[:, :2], j.truth)
    bad = j.points.copy()
    bad[3, 1] = np.nan
    with pytest.raises(FitError, match="NaN"):
        fit_elbow(bad, j.truth)
    with pytest.raises(FitError, match="covariance"):
        fit_elbow(j.points, j.truth, cov=np.ones(3))
    with pytest.raises(FitError, match=r"did not converge|stalled"):
        noisy = make_joint("a", noise=0.002, n_along=40, step_deg=6.0, rng=np.random.default_rng(0))
        from dataclasses import replace

        far = replace(noisy.truth, center=noisy.truth.center + 0.02, A=0.2)
        fit_elbow(noisy.points, far, max_iter=2, robust_start=False, fallback=False)
    assert issubclass(FitError, LrmsError)


def test_not_an_elbow_is_refused() -> None:
    rng = np.random.default_rng(4)
    # a straight pipe: both ends point the same way
    t = rng.uniform(0, 0.5, 6000)
    ang = rng.uniform(0, math.pi, 6000)
    pipe = np.column_stack([t, 0.05 * np.cos(ang), 0.05 * np.sin(ang)]) + rng.normal(0, 0.0005, (6000, 3))
    with pytest.raises(FitError, match=r"no elbow|no pipe"):
        fit_auto(pipe)
    # a flat plate
    plate = np.column_stack([rng.uniform(0, 0.3, 6000), rng.uniform(0, 0.3, 6000), rng.normal(0, 0.0005, 6000)])
    with pytest.raises(FitError):
        fit_auto(plate)
