"""The line-of-sight fit's covariance on a cloud the service fitted (docs/cylinder.md, "the
covariance near the silhouette").

``tests/data/cylinder/service-sweep-580eebfa.npz``: measurement 580eebfad28a43d9 of the simulated
rig of ``tests/service/test_calibrations.py::test_measurements_on_a_miscalibrated_rig_use_the_active_calibration``
(``rig_errors`` of that test, its ``truth`` calibration active, cylinder sweep at 20 deg/s; the
``cylinder`` scene's part is 137.5 mm). The beams (origins, directions, ranges, ``sigma_l``,
``sigma_perp``) are those the service handed to ``fit_cylinder``, cropped to the 1448 within 30 mm
of the part's surface and 20 mm of its inliers' height span; ``start_point`` / ``start_direction``:
the fitted axis rounded to 1 cm / 0.01. The service reported D - truth = -0.50 mm with a type-A
u of 0.11 mm (u_c 0.16 mm: the test's 3 u_c bound failed); over 45 sweeps of that scene the
diameters scattered by 0.40-0.47 mm.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from lrms.covariance import NoiseModel
from lrms.cylinder import Cylinder, Rays, fit_cylinder
from lrms.cylinder.lm import LosProblem
from lrms.cylinder.refine import hit_information

DATA = Path(__file__).resolve().parents[1] / "data" / "cylinder" / "service-sweep-580eebfa.npz"
TRUE_DIAMETER = 0.1375


def _sweep() -> tuple[Rays, Cylinder]:
    z = np.load(DATA)
    rays = Rays(z["origins"], z["dirs"], z["ranges"], z["sigma_l"], z["sigma_perp"])
    return rays, Cylinder(z["start_point"], z["start_direction"], 0.07)


def test_the_fits_u_on_a_service_sweep_is_of_the_scatter_over_sweeps() -> None:
    """The covariance at the solution alone gave u = 0.11 mm on this sweep (its error -0.6 mm, five
    of its u): a few beams at the model's silhouette (or just missing it) carried most of the
    information. Averaged over the parameters' uncertainty and without the miss rows, u is of the
    0.4-0.5 mm the diameters scatter over sweeps, and the error is inside 3 u."""
    rays, start = _sweep()
    fit = fit_cylinder(rays.points(), rays=rays, noise=NoiseModel(), initial=start)
    assert fit.n_inliers > 1400
    err = fit.diameter - TRUE_DIAMETER
    assert 0.3e-3 < fit.std_diameter < 1.0e-3, fit.std_diameter
    assert abs(err) < 3 * fit.std_diameter, (err, fit.std_diameter)


def test_miss_rows_carry_no_information_into_the_covariance() -> None:
    """A model a little smaller than the part: the beams at its silhouette miss it by a fraction
    of a millimetre. Their miss rows (weight ``1 / sigma_perp^2``, sigma_perp 0.07 mm) are in the
    problem's normal matrix, not in :func:`hit_information`'s, which equals the normal matrix of
    the hit beams alone."""
    rays, start = _sweep()
    fit = fit_cylinder(rays.points(), rays=rays, noise=NoiseModel(), initial=start)
    c = fit.cylinder
    small = Cylinder(c.point, c.direction, c.radius - 1e-3)
    sub = rays.subset(fit.inliers)
    _, gap = small.ray_range(sub.origins, sub.dirs)
    assert np.count_nonzero(gap > 0) >= 5
    frame = fit.frame
    full = LosProblem(sub).linearise(small, frame=frame).normal
    info = hit_information(LosProblem(sub)).linearise(small, frame=frame).normal
    hits = LosProblem(sub.subset(np.flatnonzero(gap == 0))).linearise(small, frame=frame).normal
    misses_range = hit_information(LosProblem(sub.subset(np.flatnonzero(gap > 0)))).linearise(small, frame=frame)
    np.testing.assert_allclose(info, hits + misses_range.normal, rtol=1e-9, atol=1e-9 * np.abs(hits).max())
    assert misses_range.normal[4, 4] == 0.0  # a miss beam's closest approach does not move with r
    assert full[4, 4] > 2 * info[4, 4]  # the miss rows' weight on the radius, now left out
