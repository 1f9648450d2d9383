"""The shortcuts of the cylinder fit's speed work (issue 15) give what the long way gives: the
dominant-beam screen's downdated Gauss-Newton step, the one-pass grazing sandwich, and the
screen's skip, on the short-sweep crop of ``test_cylinder_bias_continuity`` (a limb beam of
leverage 0.998 left tangent: the kind of beam the dominant-beam step exists for)."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from lrms.cylinder import pipeline
from lrms.cylinder.bias import grazing_sigmas, plain_isl, weighted_sandwich
from lrms.cylinder.lm import Linearised, LosProblem, step
from lrms.cylinder.lm import covariance as lm_covariance
from lrms.cylinder.model import Cylinder, Rays, perpendicular_frame
from lrms.cylinder.options import DetectOptions
from lrms.cylinder.refine import CylinderFit, hit_information
from tests.core.test_cylinder_bias_continuity import _tangent_fit


def _leverages(fit: CylinderFit, rays: Rays) -> tuple[Linearised, np.ndarray, np.ndarray]:
    idx = fit.inliers
    lin, jac = LosProblem.of_rows(rays, idx).linearise_dense(fit.cylinder)
    lev = np.einsum("ij,ij->i", jac @ np.linalg.inv(jac.T @ jac), jac)
    return lin, jac, lev[: idx.size] + lev[idx.size :]


def test_the_downdated_step_is_the_gauss_newton_step_without_the_beam() -> None:
    """The screen's prediction (normal equations minus the beam's rows) against a Gauss-Newton step
    solved on the inliers without that beam, for the three beams of the highest leverage."""
    fit, rays = _tangent_fit()
    idx = fit.inliers
    lin, jac, lev = _leverages(fit, rays)
    top = np.argsort(lev)[::-1][:3]
    assert lev[top[0]] > pipeline.DOMINANT_LEVERAGE
    for i in top:
        predicted = pipeline._predicted_whitened(lin, jac, fit.cylinder, rays, idx, int(i))
        without = LosProblem.of_rows(rays, np.delete(idx, i)).linearise(fit.cylinder, frame=(lin.e1, lin.e2))
        d = -np.linalg.solve(without.normal, without.gradient)
        direct = pipeline._whitened(step(fit.cylinder, without.e1, without.e2, d), rays, int(idx[i]))
        assert predicted == pytest.approx(direct, rel=1e-6, abs=1e-9)


def test_the_one_pass_sandwich_is_the_two_linearisations() -> None:
    """``weighted_sandwich`` (both normal matrices from one pass over the beams) against the
    covariance built from two full linearisations, at the fit and at a model moved 1 mm."""
    fit, rays = _tangent_fit()
    beams = LosProblem(rays)
    lat = float(fit.extra["grazing_sigma_m"])
    info = hit_information(beams)
    for cyl in (
        fit.cylinder,
        Cylinder(fit.cylinder.point, fit.cylinder.direction, fit.cylinder.radius + 1e-3),
    ):
        frame = perpendicular_frame(cyl.direction)
        sig = grazing_sigmas(cyl, rays, lat)
        a_inv = lm_covariance(info.reweighted(sig).linearise(cyl, frame=frame))
        meat = info.reweighted(np.square(sig) * plain_isl(rays)).linearise(cyl, frame=frame).normal
        expected = a_inv @ meat @ a_inv
        got = weighted_sandwich(beams, rays, cyl, lat, frame)
        assert np.max(np.abs(got - expected)) <= 1e-9 * np.max(np.abs(expected))


def test_the_screen_skips_a_refit_its_test_would_refuse(monkeypatch: pytest.MonkeyPatch) -> None:
    """The crop's limb beam (leverage 0.998) is predicted at 1.43 whitened units without it, under
    the screen's gate: screened, its refit is skipped; unscreened, the refit keeps it an inlier
    and is refused. Both leave the fit as it was."""
    fit, rays = _tangent_fit()
    pts = rays.points()
    lin, jac, lev = _leverages(fit, rays)
    i = int(np.argmax(lev))
    predicted = pipeline._predicted_whitened(lin, jac, fit.cylinder, rays, fit.inliers, i)
    assert predicted < pipeline.DOMINANT_SCREEN_GATE
    opt = DetectOptions()
    refits: list[int] = []
    los_fit = pipeline._los_fit

    def counted(*args: Any, **kw: Any) -> CylinderFit:
        refits.append(1)
        return los_fit(*args, **kw)

    monkeypatch.setattr(pipeline, "_los_fit", counted)
    unscreened = pipeline._without_dominant_beams(pts, rays, fit, opt)
    assert refits and unscreened is fit  # refitted, refused
    refits.clear()
    monkeypatch.setattr(pipeline, "DOMINANT_SCREEN_MIN", 0)
    screened = pipeline._without_dominant_beams(pts, rays, fit, opt)
    assert not refits and screened is fit  # skipped
