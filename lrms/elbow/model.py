"""The elbow-joint model of seed 000 (Eq. 1-9), with the conventions this project chose.

Model frame
-----------
A world point ``l = (x, y, z)`` maps to the model frame by Eq. 4 extended with a third rotation::

    (X, Y, Z) = R2(kappa) R3(psi) R1(omega) (l - c)

``c = (Xc, Yc, Zc)`` is the torus centre (the point on the torus axis in the bend plane). The
rotation matrices are the photogrammetric (passive, frame-rotating) ones::

    R1(a) = [[1, 0, 0], [0, cos a, sin a], [0, -sin a, cos a]]
    R2(a) = [[cos a, 0, -sin a], [0, 1, 0], [sin a, 0, cos a]]
    R3(a) = [[cos a, sin a, 0], [-sin a, cos a, 0], [0, 0, 1]]

The seed's Eq. 4 has only ``omega`` and ``psi``; those two fix the direction of the torus axis
(the model ``Y`` axis) but not where, around that axis, the bend starts. ``kappa`` (a rotation
about the model ``Y`` axis, applied last) supplies that third degree of freedom.

In the model frame the torus axis is ``Y`` and the bend lies in the ``X-Z`` plane. The tube's
centre line is

* the *start leg*: the line ``Z = A, Y = 0`` for ``X > 0`` (seed: the horizontal portion);
* the *bend*: the circle of radius ``A`` from ``theta = 90 deg`` (the ``+Z`` direction) to
  ``theta = 90 deg + d`` (``theta = atan2(Z, X)``, Eq. 3);
* the *end leg*: the tangent line leaving the bend at ``theta0 = 90 deg + d`` (seed: the
  vertical portion for ``d = 90 deg``).

Eq. 2, 5, 6 and 7 all come down to one rule: rotate the point about ``Y`` by ``pi/2 - Phi``
where ``Phi`` is ``theta`` clamped to ``[pi/2, pi/2 + d]``; then ``Zp = X cos Phi + Z sin Phi``
and ``Yp = Y``. The seed picks the clamp end by quadrant (Eq. 5 and 7); we pick it by the two
planes that bound the bend: a point is on the start side when ``X > 0`` and on the end side when
``-X sin theta0 + Z cos theta0 > 0``. A point on both sides (behind the bend, which only noise or
foreign objects reach) takes the portion whose surface is nearer. For ``A > D/2`` and points
within the tube this is exactly the seed's partition; for sharp ``0.5D`` elbows it stops noisy
points near the inner corner from being handed to the wrong portion.

Flanges (Eq. 9): ``q = 1`` on the legs. Within ``FLANGE_MARGIN * D`` of either bounding plane,
``q`` instead follows the nearer of the two radii (``D/2`` or ``Df/2``): the radius steps at the
plane, and a plane placed a millimetre off would otherwise give the flange points next to it a
residual of ``(Df - D)/2`` and the adjustment a false minimum.

The condition of Eq. 8 is ``(Zp - A)^2 + Yp^2 - Rq^2 = 0`` with ``Rq = (1-q) D/2 + q Df/2``
(``q = 1`` on the legs of a flanged joint, Eq. 9). :func:`condition_seed` evaluates that form.
The adjustment uses the equivalent :func:`condition` ``sqrt((Zp - A)^2 + Yp^2) - Rq = 0``: the
same surface (the two differ by the positive factor ``s + Rq``), hence the same least-squares
solution, but its gradient has unit length, which keeps the Gauss-Helmert normal equations well
conditioned when noise puts points near the tube's centre line.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

from lrms.errors import FitError, LrmsError

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]

#: Named joint degrees (deg).
NAMED_DEGREES = {"90": 90.0, "45": 45.0}
#: Named A/D ratios (seed: 0.5D sharp, 1D short radius, 1.5D long radius).
NAMED_RATIOS = (0.5, 1.0, 1.5)

#: Half-width (in D) of the zone around the bend's bounding planes where a flanged joint's
#: flange index q goes by the nearer radius (D/2 or Df/2) rather than by the plane alone.
FLANGE_MARGIN = 0.5

# portion labels returned by :func:`portions`
START, BEND, END = 0, 1, 2


def r1(a: float) -> FloatArray:
    """Rotation about X (passive)."""
    c, s = math.cos(a), math.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, s], [0.0, -s, c]])


def r2(a: float) -> FloatArray:
    """Rotation about Y (passive)."""
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0.0, -s], [0.0, 1.0, 0.0], [s, 0.0, c]])


def r3(a: float) -> FloatArray:
    """Rotation about Z (passive)."""
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])


def rotation_matrix(omega: float, psi: float, kappa: float = 0.0) -> FloatArray:
    """World-to-model rotation ``R2(kappa) R3(psi) R1(omega)``."""
    return r2(kappa) @ r3(psi) @ r1(omega)


def euler_from_matrix(rot: ArrayLike) -> tuple[float, float, float]:
    """Inverse of :func:`rotation_matrix`: ``(omega, psi, kappa)`` in rad, ``psi`` in [-pi/2, pi/2].

    Passive ``Ri(a)`` is the active rotation by ``-a``, so ``R = Ry(-kappa) Rz(-psi) Rx(-omega)``
    (active, intrinsic Y-Z-X).
    """
    m = np.asarray(rot, dtype=np.float64)
    if m.shape != (3, 3):
        raise LrmsError(f"rotation must be 3x3, got {m.shape}")
    a, b, c = Rotation.from_matrix(m).as_euler("YZX")
    return float(-c), float(-b), float(-a)


def skew(v: ArrayLike) -> FloatArray:
    """Cross-product matrix ``[v]x`` with ``[v]x w = v x w``."""
    x, y, z = np.asarray(v, dtype=np.float64)
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


def euler_jacobian(omega: float, psi: float, kappa: float) -> FloatArray:
    """``d(omega, psi, kappa) / d(w)`` for the small rotation ``R -> (I - [w]x) R``.

    Analytic: ``dR/de_j R^T`` is skew for each Euler angle ``e_j``; writing it as ``[s_j]x``, a
    change ``de`` gives ``dR = sum_j [s_j]x R de_j = -[w]x R`` so ``w = -S de`` with columns
    ``s_j``.
    """
    ro, rp, rk = r1(omega), r3(psi), r2(kappa)
    d1 = np.array(
        [[0.0, 0.0, 0.0], [0.0, -math.sin(omega), math.cos(omega)], [0.0, -math.cos(omega), -math.sin(omega)]]
    )
    d3 = np.array([[-math.sin(psi), math.cos(psi), 0.0], [-math.cos(psi), -math.sin(psi), 0.0], [0.0, 0.0, 0.0]])
    d2 = np.array(
        [[-math.sin(kappa), 0.0, -math.cos(kappa)], [0.0, 0.0, 0.0], [math.cos(kappa), 0.0, -math.sin(kappa)]]
    )
    rot = rk @ rp @ ro
    derivs = (rk @ rp @ d1, rk @ d3 @ ro, d2 @ rp @ ro)
    cols = []
    for dr in derivs:
        k = dr @ rot.T
        cols.append(np.array([k[2, 1], k[0, 2], k[1, 0]]))
    s = -np.column_stack(cols)
    return np.asarray(np.linalg.inv(s))


@dataclass(frozen=True)
class ElbowParams:
    """One elbow: pose, bend radius ``A``, outer diameter ``D`` and optional flange ``Df`` (m, rad).

    ``rot`` is the world-to-model rotation (``R2(kappa) R3(psi) R1(omega)``); ``degree`` the bend
    angle ``d`` (rad).
    """

    center: FloatArray
    rot: FloatArray
    A: float
    D: float
    degree: float
    Df: float | None = None

    @staticmethod
    def from_angles(
        center: ArrayLike,
        omega: float,
        psi: float,
        kappa: float,
        A: float,
        D: float,
        degree: float,
        Df: float | None = None,
    ) -> ElbowParams:
        return ElbowParams(
            np.asarray(center, dtype=np.float64).reshape(3),
            rotation_matrix(omega, psi, kappa),
            float(A),
            float(D),
            float(degree),
            None if Df is None else float(Df),
        )

    @property
    def angles(self) -> tuple[float, float, float]:
        """``(omega, psi, kappa)`` in rad."""
        return euler_from_matrix(self.rot)

    @property
    def axis(self) -> FloatArray:
        """Unit normal of the bend plane (the torus axis, model ``Y``) in world coordinates."""
        return np.asarray(self.rot[1], dtype=np.float64)

    def to_model(self, points: ArrayLike) -> FloatArray:
        pts = as_points(points)
        return np.asarray((pts - self.center) @ self.rot.T)

    def to_world(self, model_points: ArrayLike) -> FloatArray:
        m = np.asarray(model_points, dtype=np.float64)
        return np.asarray(m @ self.rot + self.center)

    def flipped(self) -> ElbowParams:
        """The same surface with start and end legs swapped (the model's two-fold symmetry).

        The swap is a half turn about the bend's bisector ``u = (cos b, 0, sin b)``,
        ``b = 90 deg + d/2``, in the model frame: ``m' = (2 u u^T - I) m``.
        """
        b = math.pi / 2 + self.degree / 2
        u = np.array([math.cos(b), 0.0, math.sin(b)])
        s = 2.0 * np.outer(u, u) - np.eye(3)
        return replace(self, rot=s @ self.rot)


def as_points(points: ArrayLike) -> FloatArray:
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise FitError(f"points must have shape (n, 3), got {pts.shape}")
    return pts


@dataclass(frozen=True)
class Evaluation:
    """Per-point quantities of the model at given parameters (model frame)."""

    m: FloatArray  # (n, 3) model coordinates
    portion: NDArray[np.int64]  # START, BEND or END
    phi: FloatArray  # Phi of Eq. 7 (clamped theta)
    zp: FloatArray  # Zp of Eq. 6
    radius: FloatArray  # Rq of Eq. 8 (D/2 or Df/2)
    q: FloatArray  # flange index of Eq. 9 (0 or 1)
    s: FloatArray  # distance from the tube's centre line
    f: FloatArray  # geometric condition s - Rq (signed distance to the surface)


def evaluate_model(m: FloatArray, A: float, D: float, degree: float, Df: float | None = None) -> Evaluation:
    """Evaluate the adapted model (Eq. 5-9) at model-frame points ``m`` (vectorized)."""
    if not 0.0 < degree <= math.pi:
        raise LrmsError(f"joint degree must be in (0, 180] deg, got {math.degrees(degree):.3f}")
    # contiguous columns: every elementwise pass below is then a plain sweep
    x, y, z = (np.ascontiguousarray(m[:, i]) for i in range(3))
    theta0 = math.pi / 2 + degree
    c0, s0 = math.cos(theta0), math.sin(theta0)
    on_start = x > 0.0
    on_end = z * c0 - x * s0 > 0.0
    r_leg = D / 2 if Df is None else Df / 2
    zp_end = x * c0 + z * s0

    # points on both sides of the bend (behind it) take the portion whose surface is nearer
    pick_start = on_start.copy()
    both = np.flatnonzero(on_start & on_end)
    if both.size:
        yb = y[both]
        s_start = np.hypot(z[both] - A, yb)
        s_end = np.hypot(zp_end[both] - A, yb)
        pick_start[both[np.abs(s_end - r_leg) < np.abs(s_start - r_leg)]] = False
    pick_end = on_end & ~pick_start
    bend = ~(pick_start | pick_end)
    bi = np.flatnonzero(bend)

    portion = np.full(x.shape, BEND, dtype=np.int64)
    portion[pick_start] = START
    portion[pick_end] = END
    xb, zb = x[bi], z[bi]
    theta = np.arctan2(zb, xb)
    theta = np.where(theta < -math.pi / 2, theta + 2 * math.pi, theta)  # (-90, 270] deg
    phi = np.full(x.shape, math.pi / 2)
    phi[pick_end] = theta0
    phi[bi] = np.clip(theta, math.pi / 2, theta0)
    zp = np.where(pick_end, zp_end, z)
    zp[bi] = np.hypot(xb, zb)
    s = np.hypot(zp - A, y)
    if Df is None:
        q = np.zeros(x.shape)
        radius = np.full(x.shape, D / 2)
    else:
        q = (~bend).astype(np.float64)
        # near the bounding planes the flange index goes by the nearer of the two radii
        margin = FLANGE_MARGIN * D
        near = (np.abs(x) < margin) | (np.abs(z * c0 - x * s0) < margin)
        q = np.where(near, (np.abs(s - Df / 2) < np.abs(s - D / 2)).astype(np.float64), q)
        radius = (1.0 - q) * D / 2 + q * (Df / 2)
    return Evaluation(m, portion, phi, zp, radius, q, s, s - radius)


def condition(points: ArrayLike, params: ElbowParams) -> FloatArray:
    """Geometric condition ``s - Rq`` per point (the signed distance to the modelled surface)."""
    ev = evaluate_model(params.to_model(points), params.A, params.D, params.degree, params.Df)
    return ev.f


def condition_seed(points: ArrayLike, params: ElbowParams) -> FloatArray:
    """The seed's algebraic condition, Eq. 8 (Eq. 1 when there is no flange)."""
    ev = evaluate_model(params.to_model(points), params.A, params.D, params.degree, params.Df)
    return np.asarray((ev.zp - params.A) ** 2 + ev.m[:, 1] ** 2 - ev.radius**2)


def portions(points: ArrayLike, params: ElbowParams) -> NDArray[np.int64]:
    """Which portion (START, BEND, END) each point is assigned to."""
    return evaluate_model(params.to_model(points), params.A, params.D, params.degree, params.Df).portion


def parse_degree(value: str | float) -> float:
    """A joint degree from the command line ('90', '45' or any number in (0, 180]) -> rad."""
    try:
        deg = float(value)
    except ValueError as exc:
        raise LrmsError(f"joint degree must be a number of degrees, got {value!r}") from exc
    if not 0.0 < deg <= 180.0:
        raise LrmsError(f"joint degree must be in (0, 180] deg, got {deg}")
    return math.radians(deg)


def parse_ratio(value: str | float | None) -> float | None:
    """An A/D ratio ('0.5', '1', '1.5', any positive number, or 'free' -> None)."""
    if value is None or (isinstance(value, str) and value.strip().lower() == "free"):
        return None
    try:
        ratio = float(value)
    except ValueError as exc:
        raise LrmsError(f"A/D ratio must be a number or 'free', got {value!r}") from exc
    if not ratio >= 0.5 - 1e-12:
        raise LrmsError(f"A/D ratio must be >= 0.5 (a torus needs A >= D/2), got {ratio}")
    return ratio
