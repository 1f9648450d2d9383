"""The second-order bias correction where a limb beam turns from a miss into a hit (docs/cylinder.md,
"Another local minimum, another bias correction").

``tests/data/cylinder/short-sweep-d991848a.npz``: measurement d991848a03bb42a5 of a short sweep
(``service.simarchive.record``, its ``SHORT_SWEEP``: -5..20 deg at 20 deg/s, 32 scans) of the simulated
rig (``seed003`` scene, the 137.5 mm part), replayed with ``service.replay.replay``: the 384 inlier beams
(origins, directions, ranges, ``sigma_l``, ``sigma_perp``) the pipeline handed to
``lrms.cylinder.bias.grazing_weighted_fit``, and that stage's starting cylinder (``start_*``). Its
range-scale re-fit (k1 = 1 %) moved the diameter 0.72 % of D off the geometry's prediction: the fit
went to another local minimum, where one limb beam (index 240) is left tangent to the model,
missing it by 0.001 ``sigma_perp``, and that beam's miss row gave 0.66 mm of the bias correction.
The ranges scaled by 1.003 (:data:`RANGE_SCALE`) put the crop's fit in that minimum.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from lrms.cylinder import Cylinder, Rays, refine_cylinder, second_order_bias
from lrms.cylinder.bias import grazing_weighted_fit
from lrms.cylinder.refine import CylinderFit

DATA = Path(__file__).resolve().parents[1] / "data" / "cylinder" / "short-sweep-d991848a.npz"
#: the range scale at which the crop's fit leaves the limb beam tangent
RANGE_SCALE = 1.003
#: the beam left tangent there
LIMB_BEAM = 240


def _tangent_fit() -> tuple[CylinderFit, Rays]:
    z = np.load(DATA)
    rays = Rays(z["origins"], z["dirs"], z["ranges"] * RANGE_SCALE, z["sigma_l"], z["sigma_perp"])
    pts = rays.points()
    start = Cylinder(z["start_point"], z["start_direction"], float(z["start_radius"]))
    fit = grazing_weighted_fit(pts, rays, refine_cylinder(pts, start, rays=rays, gate=np.inf, max_rounds=1))
    return fit, rays


def test_the_bias_correction_is_continuous_where_a_limb_beam_turns_from_miss_to_hit() -> None:
    """The data scaled by 1 +- 1e-3 about the fitted axis (the fit kept): the limb beam's miss goes
    from about -1 to +1 ``sigma_perp`` through the tangent. The diameter's correction changes by at
    most 0.1 mm (0.06 of the fit's u) from one scale to the next, 5e-5 apart. With the miss rows'
    terms in the sum it stepped by 0.73 mm at the tangent (0.72 mm on the miss side, -0.01 mm on
    the hit side)."""
    fit, rays = _tangent_fit()
    assert fit.n_inliers == rays.ranges.shape[0]
    assert fit.extra["grazing_sigma_m"] > 0
    axis = fit.cylinder.point
    sp = float(np.broadcast_to(rays.sigma_perp, rays.ranges.shape)[LIMB_BEAM])
    _, gap = fit.cylinder.ray_range(rays.origins, rays.dirs)
    assert 0.0 < gap[LIMB_BEAM] < 0.05 * sp  # the fit leaves it tangent, just missing
    corrections, misses = [], []
    for s in 1.0 + np.linspace(-1e-3, 1e-3, 41):
        scaled = Rays(axis + s * (rays.origins - axis), rays.dirs, s * rays.ranges, rays.sigma_l, rays.sigma_perp)
        _, gap = fit.cylinder.ray_range(scaled.origins, scaled.dirs)
        misses.append(gap[LIMB_BEAM] / sp)
        corrections.append(2.0 * second_order_bias(fit, scaled)[4])
    assert min(misses) == 0.0 and max(misses) > 0.5  # the beam hits at one end, misses at the other
    steps = np.abs(np.diff(corrections))
    assert steps.max() < 0.1e-3, (steps.max(), int(np.argmax(steps)))
    assert steps.max() < 0.06 * fit.std_diameter
