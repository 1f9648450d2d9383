"""Elbow fit speed: Gauss-Helmert adjustment of seed 000's model on 47,160 and ~200k points.

Run: ``.venv/bin/python -m bench.bench_elbow``. Joint a of Table 1 (90 deg, 1D, D = 0.1 m, full
coverage, 1 mm Gaussian noise, random pose). For each size it prints the time of the automatic
initial values, of the Gauss-Helmert adjustment from them (median of 3 after one warm-up run), its iterations, and, as
the baseline measured in the same run, :func:`scipy.optimize.least_squares` (trust region
reflective, the same analytic Jacobian, the same start) on the same orthogonal residuals; the
ratio baseline / ours holds up better than absolute times on a loaded machine.
Goal (issue 5): <= 0.5 s for 47,160 points on one core.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from functools import partial
from typing import TypeVar

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import least_squares

from lrms.elbow import design_matrices, fit_elbow, initial_values
from lrms.elbow.gauss_helmert import apply_update
from lrms.elbow.model import ElbowParams, condition
from sim.scene.joints import make_joint, random_pose

FloatArray = NDArray[np.float64]


T = TypeVar("T")


def _median_time(fn: Callable[[], T], repeat: int = 3) -> tuple[float, T]:
    times = []
    out = fn()
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return float(np.median(times)), out


def _scipy_fit(points: FloatArray, init: ElbowParams) -> tuple[ElbowParams, int]:
    def fun(x: FloatArray) -> FloatArray:
        return condition(points, apply_update(init, x, None, False))

    def jac(x: FloatArray) -> FloatArray:
        _, amat, _ = design_matrices(points, apply_update(init, x, None, False))
        return amat

    res = least_squares(fun, np.zeros(8), jac=jac, method="trf", x_scale="jac")
    return apply_update(init, res.x, None, False), int(res.nfev)


def main() -> None:
    rng = np.random.default_rng(1)
    print(
        f"{'points':>8} {'init s':>8} {'GH s':>8} {'iter':>5} {'scipy s':>8} {'nfev':>5} {'scipy/GH':>9} "
        f"{'|dc| um':>8} {'GH-scipy um':>11}"
    )
    for n_along in (131, 556):
        c, rot = random_pose(rng)
        j = make_joint("a", center=c, rot=rot, n_along=n_along, noise=0.001, rng=rng)
        pts = j.points
        t0 = time.perf_counter()
        init = initial_values(pts, rng=np.random.default_rng(0))
        t_init = time.perf_counter() - t0
        t_gh, fit = _median_time(partial(fit_elbow, pts, init))
        t_sp, (sp, nfev) = _median_time(partial(_scipy_fit, pts, init))
        dc = np.linalg.norm(fit.params.center - j.truth.center) * 1e6
        dd = np.linalg.norm(fit.params.center - sp.center) * 1e6
        print(
            f"{pts.shape[0]:>8} {t_init:>8.3f} {t_gh:>8.3f} {fit.iterations:>5} {t_sp:>8.3f} {nfev:>5} "
            f"{t_sp / t_gh:>9.2f} {dc:>8.1f} {dd:>11.3f}"
        )
    print("goal: GH <= 0.5 s at 47,160 points")


if __name__ == "__main__":
    main()
