"""The Monte Carlo interval (GUM Supplement 1) of a footprint fit carries the fit's own type A.

The replicas are thin-beam refits of the beams' noise; a footprint fit's type A is wider (its spot
size is estimated with a prior row, and the radius follows the cost's profile). Sweep 74 of the
bench's seed-7 stream (``tests/data/cylinder/room-sweep-seed7-074-roi.npz``, see
tests/core/test_cylinder_nominal.py): the footprint fit's u is 5.8 mm, the thin-beam replicas'
own spread 0.34 mm; before the excess was drawn, the replicas' std was 1.5 mm and their 95 %
interval [149.5, 154.5] mm against the GUM's [139.9, 163.0] mm.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np

from lrms import kinematics
from lrms.budget import BeamGeometry, SensorErrors, cylinder_budget, replica_systematics
from lrms.covariance import NoiseModel
from lrms.cylinder import BeamOptics, fit_cylinder, nominal_diameter_range, rays_from_points
from lrms.uncertainty import footprint_type_a_excess, monte_carlo_interval, thin_beam_replica_u

DATA = Path(__file__).resolve().parents[1] / "data" / "cylinder" / "room-sweep-seed7-074-roi.npz"
NM = NoiseModel()
P = kinematics.DEFAULT_P


def test_monte_carlo_of_a_footprint_fit_agrees_with_its_gum_u() -> None:
    z = np.load(DATA)
    pts = np.asarray(z["points"], dtype=np.float64)
    rays = rays_from_points(pts, P, NM)
    fit = fit_cylinder(
        pts,
        line_of_sight=True,
        p=P,
        noise=NM,
        rays=rays,
        rng=np.random.default_rng(int(z["fit_seed"])),
        optics=BeamOptics(),
        diameter_range=nominal_diameter_range(0.1375),
    )
    assert fit.extra["edge_mode_first"] >= 0, "the footprint model should win on this sweep"
    inl = rays.subset(fit.inliers)
    _, al, be = kinematics.inverse(pts[fit.inliers], P)
    beams = BeamGeometry(al, be, P, float(np.deg2rad(20.0)))
    budget = cylinder_budget(fit, inl, beams, noise=NM)
    mc = monte_carlo_interval(
        fit,
        inl,
        noise=NM,
        n=80,
        p=P,
        rng=np.random.default_rng(3),
        systematics=replica_systematics(budget, SensorErrors(), beams),
    )
    u_thin = thin_beam_replica_u(fit, inl, NM, P)
    assert u_thin < 0.5 * fit.std_diameter, (u_thin, fit.std_diameter)
    assert mc.footprint_type_a_u == footprint_type_a_excess(fit, inl, NM, P) > 0
    # the thin beam won (or no footprint model): nothing beyond the replicas' own spread
    assert footprint_type_a_excess(replace(fit, extra={**fit.extra, "edge_mode_first": -1.0}), inl, NM, P) == 0.0
    # the replicas' spread is the budget's combined u (80 replicas: the std's own error ~8 %)
    assert abs(mc.std / budget.combined - 1.0) < 0.2, (1e3 * mc.std, 1e3 * budget.combined, 1e3 * fit.std_diameter)
    assert mc.low < fit.diameter - budget.combined and mc.high > fit.diameter + budget.combined, (mc.low, mc.high)
