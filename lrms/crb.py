"""Cramer-Rao bound of the cylinder parameters for a given scan geometry and noise.

With Gaussian range noise ``sigma_l`` along known beams (the rig's noise model; the angular
terms of Eq. 5 move a beam's hit range by ``dt/dalpha sigma_alpha``, up to 2 mm against
sigma_l = 11.67 mm on the most grazing beams of a ray-cast LRMS sweep, and change the bound
by 0.3 %: they may be passed as per-beam ``sigma_l``, see docs/cylinder.md section 4),
the Fisher information of ``theta = (t1, t2, s1, s2, r)`` (see :mod:`lrms.cylinder`) is
``F = J^T J`` with ``J = d t / d theta / sigma_l``, ``t`` being the range at which each beam meets
the cylinder. Any unbiased estimator of the diameter has ``std(d) >= 2 sqrt((F^-1)_rr)``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from lrms.cylinder import Cylinder, _Frame, los_jacobian
from lrms.errors import FitError, LrmsError

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class CramerRao:
    covariance: FloatArray  # (5, 5) lower bound on the covariance of theta
    n_beams: int

    @property
    def std_diameter(self) -> float:
        return float(2.0 * np.sqrt(self.covariance[4, 4]))


def cylinder_crb(cyl: Cylinder, origins: ArrayLike, dirs: ArrayLike, sigma_l: float | ArrayLike) -> CramerRao:
    """Bound for beams ``origins``/``dirs`` ``(N, 3)`` that hit ``cyl`` (misses are ignored)."""
    o = np.asarray(origins, dtype=np.float64).reshape(-1, 3)
    d = np.asarray(dirs, dtype=np.float64).reshape(-1, 3)
    if o.shape != d.shape:
        raise LrmsError("origins and dirs must have the same shape")
    sig = np.broadcast_to(np.asarray(sigma_l, dtype=np.float64), (o.shape[0],))
    if np.any(sig <= 0):
        raise LrmsError("sigma_l must be > 0")
    _, gap = cyl.ray_range(o, d)
    hit = gap <= 0
    if np.count_nonzero(hit) < 5:
        raise FitError("fewer than 5 beams hit the cylinder: no bound")
    frame = _Frame.at(cyl)
    n = int(np.count_nonzero(hit))
    jac = los_jacobian(np.zeros(5), frame, o[hit], d[hit], sig[hit], np.ones(n))[:n]
    fisher = jac.T @ jac
    try:
        cov = np.linalg.inv(fisher)
    except np.linalg.LinAlgError as exc:  # pragma: no cover - degenerate geometry
        raise FitError("singular Fisher information (degenerate geometry)") from exc
    return CramerRao(covariance=np.asarray(cov, dtype=np.float64), n_beams=n)
