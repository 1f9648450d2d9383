"""Geometric primitives with exact, vectorized ray intersection.

Every shape answers :meth:`Shape.intersect` for ``N`` rays at once: origins ``(N, 3)`` and unit
directions ``(N, 3)`` in, the smallest ray parameter ``t > 0`` (inf for a miss) and the outward
unit surface normal at the hit out. Directions must be unit vectors, so ``t`` is the range.

Shapes: :class:`Plane` (infinite, or a finite rectangle), :class:`Cylinder` (finite, optionally
capped), :class:`Box` (oriented), :class:`Sphere` and :class:`TorusSection` (a bent tube: the
quartic of every ray is solved at once through batched companion-matrix eigenvalues, then
polished by Newton steps on the quartic).
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from lrms.errors import LrmsError

FloatArray = NDArray[np.float64]

#: Hits closer than this (m) along the ray are ignored (the ray's own start point).
T_MIN = 1e-9


class SceneError(LrmsError):
    """Bad scene or shape parameters, or badly shaped ray arrays."""


def _vec3(value: ArrayLike, what: str) -> FloatArray:
    v = np.asarray(value, dtype=np.float64)
    if v.shape != (3,) or not np.all(np.isfinite(v)):
        raise SceneError(f"{what} must be a finite 3-vector, got {value!r}")
    return v


def _unit(value: ArrayLike, what: str) -> FloatArray:
    v = _vec3(value, what)
    n = float(np.linalg.norm(v))
    if n < 1e-12:
        raise SceneError(f"{what} must be a non-zero vector")
    return v / n


def _positive(value: float, what: str) -> float:
    v = float(value)
    if not np.isfinite(v) or v <= 0:
        raise SceneError(f"{what} must be a finite positive number, got {value!r}")
    return v


def _perpendicular(a: FloatArray) -> FloatArray:
    """Some unit vector perpendicular to unit vector ``a``."""
    helper = np.array([1.0, 0.0, 0.0]) if abs(a[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    u = np.cross(a, helper)
    return np.asarray(u / np.linalg.norm(u), dtype=np.float64)


def check_rays(origins: ArrayLike, dirs: ArrayLike) -> tuple[FloatArray, FloatArray]:
    """Validate and return ``(origins, dirs)`` as float arrays of shape ``(N, 3)``."""
    o = np.asarray(origins, dtype=np.float64)
    d = np.asarray(dirs, dtype=np.float64)
    if o.ndim != 2 or o.shape[1] != 3 or d.shape != o.shape:
        raise SceneError(f"origins and dirs must both have shape (N, 3), got {o.shape} and {d.shape}")
    if d.shape[0] and not np.allclose(np.einsum("ij,ij->i", d, d), 1.0, atol=1e-9):
        raise SceneError("ray directions must be unit vectors")
    return o, d


def _dot(a: FloatArray, b: FloatArray) -> FloatArray:
    out: FloatArray = np.einsum("...i,...i->...", a, b)
    return out


class Shape(ABC):
    """A surface that rays can hit."""

    @abstractmethod
    def intersect(self, origins: FloatArray, dirs: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Smallest ``t > T_MIN`` per ray (inf: miss) and the outward unit normal there (nan: miss)."""

    @abstractmethod
    def bounding_sphere(self) -> tuple[FloatArray, float]:
        """Centre and radius of a sphere enclosing the shape (inf radius: unbounded)."""


def _select(t: FloatArray, n: FloatArray, t_new: FloatArray, n_new: FloatArray) -> None:
    """In place: where ``t_new`` is a closer valid hit, take it."""
    better = t_new < t
    t[better] = t_new[better]
    n[better] = n_new[better]


def _miss_arrays(count: int) -> tuple[FloatArray, FloatArray]:
    return np.full(count, np.inf), np.full((count, 3), np.nan)


@dataclass(frozen=True, init=False)
class Plane(Shape):
    """A plane through ``point`` with unit ``normal``; finite when ``size=(width, height)`` is given.

    The finite plane is the rectangle centred on ``point`` with its width along ``u_axis``
    (projected into the plane; default: any in-plane direction) and height along
    ``normal x u_axis``. Both faces are hit; the reported normal is ``normal`` as given.
    """

    point: FloatArray
    normal: FloatArray
    size: tuple[float, float] | None
    u_axis: FloatArray
    v_axis: FloatArray

    def __init__(
        self,
        point: ArrayLike,
        normal: ArrayLike,
        size: tuple[float, float] | None = None,
        u_axis: ArrayLike | None = None,
    ) -> None:
        n = _unit(normal, "plane normal")
        if u_axis is None:
            u = _perpendicular(n)
        else:
            u0 = _vec3(u_axis, "plane u_axis")
            u0 = u0 - np.dot(u0, n) * n
            if np.linalg.norm(u0) < 1e-12:
                raise SceneError("plane u_axis must not be parallel to the normal")
            u = u0 / np.linalg.norm(u0)
        if size is not None:
            size = (_positive(size[0], "plane width"), _positive(size[1], "plane height"))
        object.__setattr__(self, "point", _vec3(point, "plane point"))
        object.__setattr__(self, "normal", n)
        object.__setattr__(self, "size", size)
        object.__setattr__(self, "u_axis", u)
        object.__setattr__(self, "v_axis", np.cross(n, u))

    def intersect(self, origins: FloatArray, dirs: FloatArray) -> tuple[FloatArray, FloatArray]:
        denom = dirs @ self.normal
        num = (self.point - origins) @ self.normal
        with np.errstate(divide="ignore", invalid="ignore"):
            t = num / denom
        ok = (denom != 0) & (t > T_MIN)
        if self.size is not None:
            hit = origins + np.where(ok, t, 0.0)[:, None] * dirs - self.point
            ok &= (np.abs(hit @ self.u_axis) <= self.size[0] / 2) & (np.abs(hit @ self.v_axis) <= self.size[1] / 2)
        t_out = np.where(ok, t, np.inf)
        n_out = np.where(ok[:, None], self.normal, np.nan)
        return t_out, n_out

    def bounding_sphere(self) -> tuple[FloatArray, float]:
        if self.size is None:
            return self.point, float("inf")
        return self.point, float(np.hypot(*self.size) / 2)


@dataclass(frozen=True, init=False)
class Sphere(Shape):
    """A sphere of ``radius`` about ``center``."""

    center: FloatArray
    radius: float

    def __init__(self, center: ArrayLike, radius: float) -> None:
        object.__setattr__(self, "center", _vec3(center, "sphere centre"))
        object.__setattr__(self, "radius", _positive(radius, "sphere radius"))

    def intersect(self, origins: FloatArray, dirs: FloatArray) -> tuple[FloatArray, FloatArray]:
        oc = origins - self.center
        half_b = _dot(oc, dirs)
        c = _dot(oc, oc) - self.radius**2
        disc = half_b * half_b - c
        ok = disc >= 0
        root = np.sqrt(np.where(ok, disc, 0.0))
        t1, t2 = -half_b - root, -half_b + root
        t = np.where(t1 > T_MIN, t1, np.where(t2 > T_MIN, t2, np.inf))
        t = np.where(ok, t, np.inf)
        hit = np.isfinite(t)
        p = origins + np.where(hit, t, 0.0)[:, None] * dirs
        n = np.where(hit[:, None], (p - self.center) / self.radius, np.nan)
        return t, n

    def bounding_sphere(self) -> tuple[FloatArray, float]:
        return self.center, self.radius


@dataclass(frozen=True, init=False)
class Cylinder(Shape):
    """A finite circular cylinder: axis from ``point`` (the centre of one end) along ``direction``.

    ``length`` is the axis length; with ``capped`` (default) the two end discs are surfaces too.
    """

    point: FloatArray
    direction: FloatArray
    radius: float
    length: float
    capped: bool

    def __init__(
        self, point: ArrayLike, direction: ArrayLike, radius: float, length: float, capped: bool = True
    ) -> None:
        object.__setattr__(self, "point", _vec3(point, "cylinder axis point"))
        object.__setattr__(self, "direction", _unit(direction, "cylinder axis direction"))
        object.__setattr__(self, "radius", _positive(radius, "cylinder radius"))
        object.__setattr__(self, "length", _positive(length, "cylinder length"))
        object.__setattr__(self, "capped", bool(capped))

    def intersect(self, origins: FloatArray, dirs: FloatArray) -> tuple[FloatArray, FloatArray]:
        a = self.direction
        rel = origins - self.point
        oa = rel @ a
        da = dirs @ a
        o_perp = rel - oa[:, None] * a
        d_perp = dirs - da[:, None] * a
        qa = _dot(d_perp, d_perp)
        qb = 2.0 * _dot(o_perp, d_perp)
        qc = _dot(o_perp, o_perp) - self.radius**2
        disc = qb * qb - 4.0 * qa * qc
        ok = (qa > 1e-300) & (disc >= 0)
        root = np.sqrt(np.where(ok, disc, 0.0))
        # Numerically stable roots: q = -(b + sign(b) sqrt(disc)) / 2; t1 = q / a, t2 = c / q.
        q = -0.5 * (qb + np.copysign(root, qb))
        with np.errstate(divide="ignore", invalid="ignore"):
            r1 = q / qa
            r2 = np.where(q != 0, qc / q, r1)
        t, n = _miss_arrays(len(origins))
        for r in (r1, r2):
            h = oa + r * da
            valid = ok & (r > T_MIN) & (h >= 0) & (h <= self.length)
            rr = np.where(valid, r, np.inf)
            p_perp = o_perp + np.where(valid, r, 0.0)[:, None] * d_perp
            _select(t, n, rr, p_perp / self.radius)
        if self.capped:
            for level, sign in ((0.0, -1.0), (self.length, 1.0)):
                with np.errstate(divide="ignore", invalid="ignore"):
                    r = (level - oa) / da
                valid = (da != 0) & (r > T_MIN)
                p_perp = o_perp + np.where(valid, r, 0.0)[:, None] * d_perp
                valid &= _dot(p_perp, p_perp) <= self.radius**2
                _select(t, n, np.where(valid, r, np.inf), np.broadcast_to(sign * a, n.shape))
        return t, n

    def bounding_sphere(self) -> tuple[FloatArray, float]:
        return self.point + self.direction * self.length / 2, float(np.hypot(self.radius, self.length / 2))


@dataclass(frozen=True, init=False)
class Box(Shape):
    """An oriented box: ``center``, full ``size`` (3,), and ``rotation`` (3x3, columns = box axes)."""

    center: FloatArray
    size: FloatArray
    rotation: FloatArray

    def __init__(self, center: ArrayLike, size: ArrayLike, rotation: ArrayLike | None = None) -> None:
        s = _vec3(size, "box size")
        if np.any(s <= 0):
            raise SceneError(f"box size must be positive, got {size!r}")
        rot = np.eye(3) if rotation is None else np.asarray(rotation, dtype=np.float64)
        if rot.shape != (3, 3) or not np.allclose(rot @ rot.T, np.eye(3), atol=1e-9) or np.linalg.det(rot) < 0:
            raise SceneError("box rotation must be a proper 3x3 rotation matrix")
        object.__setattr__(self, "center", _vec3(center, "box centre"))
        object.__setattr__(self, "size", s)
        object.__setattr__(self, "rotation", rot)

    def intersect(self, origins: FloatArray, dirs: FloatArray) -> tuple[FloatArray, FloatArray]:
        o = (origins - self.center) @ self.rotation
        d = dirs @ self.rotation
        h = self.size / 2
        parallel = d == 0
        with np.errstate(divide="ignore", invalid="ignore"):
            t1 = (-h - o) / d
            t2 = (h - o) / d
        inside_slab = np.abs(o) <= h
        lo = np.where(parallel, np.where(inside_slab, -np.inf, np.inf), np.minimum(t1, t2))
        hi = np.where(parallel, np.where(inside_slab, np.inf, -np.inf), np.maximum(t1, t2))
        k_near = np.argmax(lo, axis=1)
        k_far = np.argmin(hi, axis=1)
        rows = np.arange(len(o))
        t_near = lo[rows, k_near]
        t_far = hi[rows, k_far]
        ok = (t_near <= t_far) & (t_far > T_MIN)
        entering = t_near > T_MIN
        t = np.where(ok, np.where(entering, t_near, t_far), np.inf)
        k = np.where(entering, k_near, k_far)
        sign = np.where(entering, -np.sign(d[rows, k]), np.sign(d[rows, k]))
        n_local = np.zeros_like(o)
        n_local[rows, k] = sign
        n = np.where(ok[:, None], n_local @ self.rotation.T, np.nan)
        return t, n

    def bounding_sphere(self) -> tuple[FloatArray, float]:
        return self.center, float(np.linalg.norm(self.size) / 2)


@dataclass(frozen=True, init=False)
class TorusSection(Shape):
    """A section of a torus: a bent tube (pipe elbow).

    ``center``: centre of the bend; ``axis``: unit normal of the bend plane; ``bend_radius`` (A):
    centre to tube centre line; ``tube_radius`` (D/2); the section covers the angles
    ``[0, extent]`` (rad, right-handed about ``axis``) measured from ``start`` (a direction in the
    bend plane; default: any). ``extent = 2 pi`` is the whole torus.
    """

    center: FloatArray
    axis: FloatArray
    bend_radius: float
    tube_radius: float
    extent: float
    start: FloatArray
    _frame: FloatArray

    def __init__(
        self,
        center: ArrayLike,
        axis: ArrayLike,
        bend_radius: float,
        tube_radius: float,
        extent: float = 2 * np.pi,
        start: ArrayLike | None = None,
    ) -> None:
        ax = _unit(axis, "torus axis")
        if start is None:
            e1 = _perpendicular(ax)
        else:
            s0 = _vec3(start, "torus start direction")
            s0 = s0 - np.dot(s0, ax) * ax
            if np.linalg.norm(s0) < 1e-12:
                raise SceneError("torus start direction must not be parallel to its axis")
            e1 = s0 / np.linalg.norm(s0)
        ext = _positive(extent, "torus extent")
        if ext > 2 * np.pi + 1e-12:
            raise SceneError(f"torus extent must be at most 2 pi, got {extent!r}")
        object.__setattr__(self, "center", _vec3(center, "torus centre"))
        object.__setattr__(self, "axis", ax)
        object.__setattr__(self, "bend_radius", _positive(bend_radius, "torus bend radius"))
        object.__setattr__(self, "tube_radius", _positive(tube_radius, "torus tube radius"))
        object.__setattr__(self, "extent", min(ext, 2 * np.pi))
        object.__setattr__(self, "start", e1)
        # Columns: e1 (start), e2 = axis x e1, axis: local (x, y, z).
        object.__setattr__(self, "_frame", np.column_stack([e1, np.cross(ax, e1), ax]))

    def _local(self, origins: FloatArray, dirs: FloatArray) -> tuple[FloatArray, FloatArray]:
        return (origins - self.center) @ self._frame, dirs @ self._frame

    def angle_of(self, points: FloatArray) -> FloatArray:
        """Angle in ``[0, 2 pi)`` of points about the axis, measured from ``start``."""
        loc = (np.asarray(points, dtype=np.float64) - self.center) @ self._frame
        return np.mod(np.arctan2(loc[..., 1], loc[..., 0]), 2 * np.pi)

    def intersect(self, origins: FloatArray, dirs: FloatArray) -> tuple[FloatArray, FloatArray]:
        count = len(origins)
        t_out, n_out = _miss_arrays(count)
        if count == 0:
            return t_out, n_out
        o, d = self._local(origins, dirs)
        big_a, r = self.bend_radius, self.tube_radius
        # Re-centre every ray at its point closest to the torus centre: keeps the quartic well
        # conditioned for far-away origins. Solve in s = t - s0.
        s0 = -_dot(o, d)
        o = o + s0[:, None] * d
        # (|p|^2 + A^2 - r^2)^2 = 4 A^2 (px^2 + py^2), with p = o + s d and |d| = 1.
        g = _dot(o, o) + big_a**2 - r**2
        h = _dot(o, d)  # zero after re-centring, kept for clarity
        dxy = d[:, 0] ** 2 + d[:, 1] ** 2
        oxy = o[:, 0] * d[:, 0] + o[:, 1] * d[:, 1]
        oo = o[:, 0] ** 2 + o[:, 1] ** 2
        c3 = 4.0 * h
        c2 = 4.0 * h * h + 2.0 * g - 4.0 * big_a**2 * dxy
        c1 = 4.0 * h * g - 8.0 * big_a**2 * oxy
        c0 = g * g - 4.0 * big_a**2 * oo
        # Batched companion matrices of the monic quartic s^4 + c3 s^3 + c2 s^2 + c1 s + c0.
        comp = np.zeros((count, 4, 4))
        comp[:, 1, 0] = comp[:, 2, 1] = comp[:, 3, 2] = 1.0
        comp[:, 0, 0] = -c3
        comp[:, 0, 1] = -c2
        comp[:, 0, 2] = -c1
        comp[:, 0, 3] = -c0
        roots = np.linalg.eigvals(comp)  # (N, 4) complex
        scale = big_a + r
        # Keep (nearly) real roots: grazing rays give double roots whose imaginary parts are of
        # the order of sqrt(eps) * scale; a polished root is then validated on the surface.
        s = roots.real.copy()
        candidate = np.abs(roots.imag) <= 1e-5 * scale
        coeffs = (c3[:, None], c2[:, None], c1[:, None], c0[:, None])
        for _ in range(3):
            f = (((s + coeffs[0]) * s + coeffs[1]) * s + coeffs[2]) * s + coeffs[3]
            df = ((4.0 * s + 3.0 * coeffs[0]) * s + 2.0 * coeffs[1]) * s + coeffs[2]
            with np.errstate(divide="ignore", invalid="ignore"):
                step = np.where(np.abs(df) > 0, f / df, 0.0)
            s = np.where(np.isfinite(step) & (np.abs(step) < 1e-3 * scale), s - step, s)
        t = s + s0[:, None]
        p = o[:, None, :] + s[..., None] * d[:, None, :]  # (N, 4, 3) local hit points
        rho = np.hypot(p[..., 0], p[..., 1])
        on_surface = np.abs(np.hypot(rho - big_a, p[..., 2]) - r) <= 1e-7 * scale
        phi = np.mod(np.arctan2(p[..., 1], p[..., 0]), 2 * np.pi)
        in_section = (phi <= self.extent) | (self.extent >= 2 * np.pi)
        valid = candidate & on_surface & in_section & (t > T_MIN)
        t_valid = np.where(valid, t, np.inf)
        k = np.argmin(t_valid, axis=1)
        rows = np.arange(count)
        t_out = t_valid[rows, k]
        hit = np.isfinite(t_out)
        ph = p[rows, k]
        rho_h = rho[rows, k]
        with np.errstate(divide="ignore", invalid="ignore"):
            ring = np.stack([ph[:, 0] / rho_h * big_a, ph[:, 1] / rho_h * big_a, np.zeros(count)], axis=1)
        n_local = (ph - ring) / r
        n_local /= np.linalg.norm(n_local, axis=1, keepdims=True)
        n_out = np.where(hit[:, None], n_local @ self._frame.T, np.nan)
        return t_out, n_out

    def bounding_sphere(self) -> tuple[FloatArray, float]:
        return self.center, self.bend_radius + self.tube_radius
