"""The cylinder model and the beams: geometry, ray/cylinder intersection, rays recovered from
points (Eq. 1 inverted), neighbourhood normals."""

from __future__ import annotations

import math
import os
import threading
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from lrms import kinematics
from lrms.covariance import NoiseModel
from lrms.errors import FitError

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]

#: Floor (m) of the lateral standard deviation that scales a beam's miss distance. The
#: angular noise alone (``l sigma_alpha``, 0.08 mm at 2.5 m) would make the fit hostage to the
#: last fraction of a millimetre at the silhouette, where real returns are mixed pixels of a
#: spot tens of mm wide; 1 mm keeps the objective continuous without trusting that edge.
SILHOUETTE_SIGMA = 1e-3


def _dot(a: FloatArray, b: FloatArray) -> FloatArray:
    """Inner products over the last axis (broadcasting); faster than ``np.sum(a * b, -1)``."""
    return np.asarray(np.einsum("...i,...i->...", a, b), dtype=np.float64)


def _unit(v: ArrayLike) -> FloatArray:
    a = np.asarray(v, dtype=np.float64)
    return np.asarray(a / np.linalg.norm(a, axis=-1, keepdims=True), dtype=np.float64)


def perpendicular_frame(w: ArrayLike) -> tuple[FloatArray, FloatArray]:
    """Two unit vectors ``e1, e2`` with ``(e1, e2, w)`` right-handed and orthonormal."""
    # scalar arithmetic (this runs in every iteration of the fits): the same vectors as
    # e1 = unit(helper x w), e2 = w x e1 with helper = x (or y when w is near x)
    x, y, z = (float(c) for c in np.asarray(w, dtype=np.float64).reshape(3))
    n = math.sqrt(x * x + y * y + z * z)
    x, y, z = x / n, y / n, z / n
    if abs(x) < 0.9:  # helper (1, 0, 0): helper x w = (0, -z, y)
        m = math.sqrt(z * z + y * y)
        a0, a1, a2 = 0.0, -z / m, y / m
    else:  # helper (0, 1, 0): helper x w = (z, 0, -x)
        m = math.sqrt(z * z + x * x)
        a0, a1, a2 = z / m, 0.0, -x / m
    e1 = np.array([a0, a1, a2])
    e2 = np.array([y * a2 - z * a1, z * a0 - x * a2, x * a1 - y * a0])
    return e1, e2


@dataclass(frozen=True)
class Cylinder:
    """An infinite circular cylinder: a point on the axis, the unit axis direction, the radius."""

    point: FloatArray
    direction: FloatArray
    radius: float

    def __post_init__(self) -> None:
        p = np.asarray(self.point, dtype=np.float64).reshape(3)
        d = np.asarray(self.direction, dtype=np.float64).reshape(3)
        nd = float(np.linalg.norm(d))
        if not (np.all(np.isfinite(p)) and np.isfinite(nd) and nd > 0 and np.isfinite(self.radius)):
            raise FitError("cylinder parameters must be finite with a non-zero axis direction")
        if self.radius <= 0:
            raise FitError(f"cylinder radius must be > 0, got {self.radius}")
        object.__setattr__(self, "point", p)
        object.__setattr__(self, "direction", d / nd)
        object.__setattr__(self, "radius", float(self.radius))

    @classmethod
    def trusted(cls, point: FloatArray, direction: FloatArray, radius: float) -> Cylinder:
        """A cylinder from parameters the caller has checked (float64 ``(3,)`` arrays, a unit
        direction, a finite radius > 0): no validation (the fits' inner loops build one per step)."""
        new = object.__new__(cls)
        object.__setattr__(new, "point", point)
        object.__setattr__(new, "direction", direction)
        object.__setattr__(new, "radius", float(radius))
        return new

    @property
    def diameter(self) -> float:
        return 2.0 * self.radius

    def radial(self, points: ArrayLike) -> FloatArray:
        """Component of ``points - point`` perpendicular to the axis, ``(N, 3)``."""
        v = np.asarray(points, dtype=np.float64) - self.point
        return np.asarray(v - (v @ self.direction)[..., None] * self.direction, dtype=np.float64)

    def axis_distance(self, points: ArrayLike) -> FloatArray:
        pts = np.asarray(points, dtype=np.float64)
        if pts.ndim != 2 or pts.shape[1] != 3:
            return np.asarray(np.linalg.norm(self.radial(pts), axis=-1), dtype=np.float64)
        # by coordinate, no (N, 3) temporaries (the pipeline measures every point of the cloud
        # against a candidate several times)
        a, w = self.point, self.direction
        x, y, z = pts[:, 0] - a[0], pts[:, 1] - a[1], pts[:, 2] - a[2]
        h = x * w[0] + y * w[1] + z * w[2]
        x -= h * w[0]
        y -= h * w[1]
        z -= h * w[2]
        return np.asarray(np.sqrt(x * x + y * y + z * z), dtype=np.float64)

    def surface_distance(self, points: ArrayLike) -> FloatArray:
        """Signed orthogonal distance to the surface (positive outside)."""
        return self.axis_distance(points) - self.radius

    def ray_range(self, origins: ArrayLike, dirs: ArrayLike) -> tuple[FloatArray, FloatArray]:
        """Range at which unit rays first meet the surface, and the miss distance.

        Returns ``(t, gap)``: for a hit, ``t`` is the near intersection and ``gap`` is 0; for a
        miss, ``t`` is the range of closest approach to the axis and ``gap`` (> 0) how far the
        ray passes outside the surface there.
        """
        o = np.asarray(origins, dtype=np.float64)
        u = np.asarray(dirs, dtype=np.float64)
        if o.ndim == 2 and u.shape == o.shape and o.shape[1] == 3:
            return _ray_cylinder_rows(o, u, self.point, self.direction, self.radius)
        t, gap = _ray_cylinder(o, u, self.point, self.direction, np.asarray(self.radius))
        return t, gap

    def with_point_near(self, reference: ArrayLike) -> Cylinder:
        """Same cylinder with its axis point moved to the foot of ``reference`` on the axis."""
        ref = np.asarray(reference, dtype=np.float64)
        a = self.point + float((ref - self.point) @ self.direction) * self.direction
        return Cylinder(a, self.direction, self.radius)


#: Beams per block of :func:`_ray_cylinder_rows` (its temporaries stay in the CPU's cache).
RAY_BLOCK = 16384


def _ray_cylinder_rows(
    o: FloatArray, u: FloatArray, a: FloatArray, w: FloatArray, r: float
) -> tuple[FloatArray, FloatArray]:
    """:func:`_ray_cylinder` for ``(N, 3)`` beams and one cylinder, by coordinate (no ``(N, 3)``
    temporaries; the pipeline calls it on every beam of the cloud several times), in blocks of
    :data:`RAY_BLOCK` beams."""
    n = o.shape[0]
    if n <= RAY_BLOCK:
        return _ray_cylinder_block(o, u, a, w, r)
    t, gap = np.empty(n), np.empty(n)
    for s in range(0, n, RAY_BLOCK):
        t[s : s + RAY_BLOCK], gap[s : s + RAY_BLOCK] = _ray_cylinder_block(
            o[s : s + RAY_BLOCK], u[s : s + RAY_BLOCK], a, w, r
        )
    return t, gap


def _ray_cylinder_block(
    o: FloatArray, u: FloatArray, a: FloatArray, w: FloatArray, r: float
) -> tuple[FloatArray, FloatArray]:
    v0, v1, v2 = o[:, 0] - a[0], o[:, 1] - a[1], o[:, 2] - a[2]
    u0, u1, u2 = u[:, 0], u[:, 1], u[:, 2]
    vw = v0 * w[0] + v1 * w[1] + v2 * w[2]
    uw = u0 * w[0] + u1 * w[1] + u2 * w[2]
    aa = np.maximum(u0 * u0 + u1 * u1 + u2 * u2 - uw * uw, 1e-300)
    bb = v0 * u0 + v1 * u1 + v2 * u2 - vw * uw
    cc = v0 * v0 + v1 * v1 + v2 * v2 - vw * vw
    t_ca = -bb / aa
    d_ca2 = np.maximum(cc - bb * bb / aa, 0.0)
    disc = aa * (r * r - d_ca2)
    hit = disc >= 0
    t = np.where(hit, t_ca - np.sqrt(np.where(hit, disc, 0.0)) / aa, t_ca)
    gap = np.where(hit, 0.0, np.sqrt(d_ca2) - r)
    return np.asarray(t, dtype=np.float64), np.asarray(gap, dtype=np.float64)


def _ray_cylinder(
    o: FloatArray, u: FloatArray, a: FloatArray, w: FloatArray, r: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """Broadcasting core of :meth:`Cylinder.ray_range`.

    ``o, u``: ``(..., N, 3)``; ``a, w``: ``(..., 3)`` (one axis per leading index); ``r``: ``(...)``.
    """
    a_ = a[..., None, :]
    w_ = w[..., None, :]
    v = o - a_
    vp = v - _dot(v, w_)[..., None] * w_
    up = u - _dot(u, w_)[..., None] * w_
    aa = np.maximum(_dot(up, up), 1e-300)
    bb = _dot(vp, up)
    cc = _dot(vp, vp)
    t_ca = -bb / aa
    d_ca2 = np.maximum(cc - bb * bb / aa, 0.0)
    rr = np.asarray(r, dtype=np.float64)[..., None]
    disc = aa * (rr * rr - d_ca2)
    hit = disc >= 0
    t = np.where(hit, t_ca - np.sqrt(np.where(hit, disc, 0.0)) / aa, t_ca)
    gap = np.where(hit, 0.0, np.sqrt(d_ca2) - rr)
    return np.asarray(t, dtype=np.float64), np.asarray(gap, dtype=np.float64)


# --------------------------------------------------------------------------- rays & normals


@dataclass(frozen=True)
class Rays:
    """Beams of the measured points: origins ``(N, 3)``, unit directions ``(N, 3)``, ranges ``(N,)``,
    and per-point standard deviations along (``sigma_l``) and across (``sigma_perp``) the beam."""

    origins: FloatArray
    dirs: FloatArray
    ranges: FloatArray
    sigma_l: FloatArray
    sigma_perp: FloatArray

    def subset(self, idx: ArrayLike) -> Rays:
        i = np.asarray(idx)
        return Rays(self.origins[i], self.dirs[i], self.ranges[i], self.sigma_l[i], self.sigma_perp[i])

    def points(self) -> FloatArray:
        return np.asarray(self.origins + self.ranges[:, None] * self.dirs, dtype=np.float64)


def rays_from_points(points: ArrayLike, p: float = kinematics.DEFAULT_P, noise: NoiseModel | None = None) -> Rays:
    """Recover each rig-frame point's beam by inverting Eq. 1 (the rig at the origin)."""
    nm = noise if noise is not None else NoiseModel()
    pts = np.asarray(points, dtype=np.float64)
    l, alpha, beta = kinematics.inverse(pts, p)
    origins, dirs = kinematics.beam_rays(alpha, beta, p)
    lat = np.hypot(l * nm.sigma_alpha, (l * np.sin(alpha) + p) * nm.sigma_beta)
    return Rays(
        origins=origins,
        dirs=dirs,
        ranges=l,
        sigma_l=np.full(l.shape, nm.sigma_l),
        sigma_perp=np.maximum(lat, SILHOUETTE_SIGMA),
    )


#: Which k-d tree :func:`estimate_normals` searches with: ``"auto"`` is pykdtree when it is
#: installed, else scipy's ``cKDTree``; both return the exact k nearest neighbours.
KnnBackend = Literal["auto", "pykdtree", "scipy"]
_KNN_BACKENDS: tuple[str, ...] = ("auto", "pykdtree", "scipy")

_PYKDTREE_LOCK = threading.Lock()
_pykdtree_class: list[Any] = []  # [KDTree or None] once the import was tried


def _pykdtree() -> Any:
    """pykdtree's ``KDTree``, imported on first use (about 1 ms, against 0.3 s for
    :mod:`scipy.spatial`); ``None`` when it is not installed.

    pykdtree parallelises its queries with OpenMP, by default on every core. The pykdtree wheel
    bundles its own libgomp, which reads ``OMP_NUM_THREADS`` once, when it is loaded. So unless
    the variable holds a value (an empty ``OMP_NUM_THREADS=""`` counts as unset: libgomp would
    use every core), the import runs with ``OMP_NUM_THREADS=1`` and the variable is put back as
    it was right after; pykdtree's queries then run on the calling thread alone, like scipy's
    (the fits already run one per core in the service and the reprocessing workers).
    ``OMP_NUM_THREADS=N`` before the first fit asks for N threads.

    Limits, plainly: the pin lasts only for the import, and only the first import counts.

    * It writes ``os.environ`` of the whole process for that moment; another thread that reads
      the environment or loads an OpenMP runtime (or forks) just then sees ``1``. The lock
      below serialises only the callers of this function.
    * An OpenMP runtime shared with pykdtree (a libgomp loaded before, e.g. by a build of
      pykdtree linked against the system's) has already read the variable: the pin does nothing
      then and the queries take its thread count.
    * Setting or changing ``OMP_NUM_THREADS`` after the first fit has no effect.

    The CLI commands ``lrms serve``, ``measure``, ``replay`` and ``reprocess`` (and their worker
    processes) ``setdefault`` ``OMP_NUM_THREADS=1`` at the start of their run, before the fit
    modules are imported, so there the variable is already set and this function leaves the
    environment alone (unless it was exported empty: ``setdefault`` keeps that).
    """
    with _PYKDTREE_LOCK:
        if not _pykdtree_class:
            before = os.environ.get("OMP_NUM_THREADS")
            pinned = not (before or "").strip()
            if pinned:
                os.environ["OMP_NUM_THREADS"] = "1"
            try:
                from pykdtree.kdtree import KDTree

                _pykdtree_class.append(KDTree)
            except ImportError:
                _pykdtree_class.append(None)
            finally:
                if pinned:
                    if before is None:
                        os.environ.pop("OMP_NUM_THREADS", None)
                    else:
                        os.environ["OMP_NUM_THREADS"] = before
        return _pykdtree_class[0]


def _finite_rows(a: FloatArray, what: str, dims: int | None = None) -> None:
    """Raise :class:`FitError` unless ``a`` is ``(n, dims)`` and finite."""
    if a.ndim != 2 or (dims is not None and a.shape[1] != dims):
        want = f"(n, {dims})" if dims is not None else "(n, d)"
        raise FitError(f"{what} must be a {want} array, got shape {a.shape}")
    if not np.isfinite(a).all():
        bad = int(np.count_nonzero(~np.isfinite(a).all(axis=1)))
        raise FitError(f"{what} must be finite: {bad} of {a.shape[0]} rows hold NaN or inf")


def knn_query(points: ArrayLike, backend: KnnBackend = "auto") -> Callable[[ArrayLike, int], IntArray]:
    """A k-d tree over ``points`` (``(n, d)``, searched in float64) as ``query(q, k)`` -> the
    indices ``(m, k)`` (``intp``) of each query point's ``k`` nearest points, nearest first.

    ``backend="auto"`` takes pykdtree when installed, else scipy's ``cKDTree`` (imported on first
    use). Both are exact and, for distinct distances, return the same indices in the same
    order; where several points lie at exactly the same distance (duplicates, lattices) each
    may pick a different one of them, as either might on another build.

    Raises :class:`~lrms.errors.FitError` for an unknown ``backend``, points or query points
    that are not finite or not ``(n, d)`` / ``(m, d)``, and ``k`` outside ``2 <= k <= n`` (the
    backends would otherwise give a 1-D result for ``k = 1`` and, for ``k > n``, pad with an
    out-of-range index: ``n`` from cKDTree, 2**32 - 1 from pykdtree); ``ModuleNotFoundError``
    for ``backend="pykdtree"`` when pykdtree is not installed.
    """
    if backend not in _KNN_BACKENDS:
        raise FitError(f"unknown k-nearest-neighbour backend {backend!r}; expected one of {_KNN_BACKENDS}")
    pts = np.ascontiguousarray(points, dtype=np.float64)
    _finite_rows(pts, "k-d tree points")
    n, dims = pts.shape

    def checked(q: ArrayLike, k: int) -> tuple[FloatArray, int]:
        qq = np.ascontiguousarray(q, dtype=np.float64)
        _finite_rows(qq, "query points", dims)
        if isinstance(k, bool) or not isinstance(k, (int, np.integer)) or not 2 <= k <= n:
            raise FitError(f"k must be an integer with 2 <= k <= n = {n} (points in the tree), got {k!r}")
        return qq, int(k)

    kd = _pykdtree() if backend != "scipy" else None
    if backend == "pykdtree" and kd is None:
        raise ModuleNotFoundError("the pykdtree k-nearest-neighbour backend is not installed (pip install pykdtree)")
    if kd is not None:
        tree: Any = kd(pts, leafsize=16)
    else:
        from scipy.spatial import cKDTree  # 0.3 s of imports: only without pykdtree

        tree = cKDTree(pts, leafsize=16)

    def query(q: ArrayLike, k: int) -> IntArray:
        qq, kk = checked(q, k)
        _, idx = tree.query(qq, k=kk)
        return np.asarray(idx, dtype=np.intp).reshape(qq.shape[0], kk)

    return query


def estimate_normals(
    points: ArrayLike, k: int = 24, chunk: int = 50_000, *, backend: KnnBackend = "auto"
) -> FloatArray:
    """Unit normals by PCA of each point's ``k`` nearest neighbours (smallest-eigenvalue axis);
    the neighbours from :func:`knn_query` (``backend``). ``k`` is clamped to ``3 <= k <= n``.
    Raises :class:`~lrms.errors.FitError` for fewer than 3 points, points that are not a finite
    ``(n, 3)`` array, or an unknown ``backend``."""
    pts = np.asarray(points, dtype=np.float64)
    _finite_rows(pts, "points for normals", 3)
    n = pts.shape[0]
    if n < 3:
        raise FitError(f"need at least 3 points for normals, got {n}")
    kk = int(min(max(k, 3), n))
    query = knn_query(pts, backend)
    cols = np.ascontiguousarray(pts.T)
    out = np.empty_like(pts)
    for s in range(0, n, chunk):
        idx = query(pts[s : s + chunk], kk)
        # the neighbourhoods' covariances from the six second moments, by coordinate (an
        # ``(n, k, 3)`` einsum took three times as long)
        x = cols[:, idx]  # (3, n, k)
        m = x.mean(axis=-1)
        cov = np.empty((idx.shape[0], 3, 3))
        for i in range(3):
            for j in range(i, 3):
                c = np.einsum("nk,nk->n", x[i], x[j]) / kk - m[i] * m[j]
                cov[:, i, j] = c
                cov[:, j, i] = c
        out[s : s + chunk] = smallest_eigenvectors(cov)
    return out


def smallest_eigenvectors(cov: FloatArray) -> FloatArray:
    """Unit eigenvectors ``(n, 3)`` of the smallest eigenvalues of symmetric ``(n, 3, 3)``
    matrices, in closed form (several times faster than ``np.linalg.eigh`` on many small
    matrices): the eigenvalue by the trigonometric solution of the characteristic cubic, the
    vector as the largest cross product of two rows of ``A - lambda I``. Where the two smallest
    eigenvalues coincide the vector is any one of their plane (as is ``eigh``'s)."""
    a00, a11, a22 = cov[:, 0, 0], cov[:, 1, 1], cov[:, 2, 2]
    a01, a02, a12 = cov[:, 0, 1], cov[:, 0, 2], cov[:, 1, 2]
    q = (a00 + a11 + a22) / 3.0
    b00, b11, b22 = a00 - q, a11 - q, a22 - q
    p2 = (b00 * b00 + b11 * b11 + b22 * b22 + 2.0 * (a01 * a01 + a02 * a02 + a12 * a12)) / 6.0
    p = np.sqrt(np.maximum(p2, 1e-100))  # p**3 stays a normal number
    det = b00 * (b11 * b22 - a12 * a12) - a01 * (a01 * b22 - a12 * a02) + a02 * (a01 * a12 - b11 * a02)
    half = np.clip(det / (2.0 * p * p * p), -1.0, 1.0)
    lam = q + 2.0 * p * np.cos(np.arccos(half) / 3.0 + 2.0 * np.pi / 3.0)
    m0 = np.stack([a00 - lam, a01, a02], axis=1)
    m1 = np.stack([a01, a11 - lam, a12], axis=1)
    m2 = np.stack([a02, a12, a22 - lam], axis=1)
    cands = np.stack([np.cross(m0, m1), np.cross(m0, m2), np.cross(m1, m2)], axis=1)  # (n, 3, 3)
    norms = np.einsum("nki,nki->nk", cands, cands)
    best = np.argmax(norms, axis=1)
    rows = np.arange(cov.shape[0])
    vec = cands[rows, best]
    nrm = np.sqrt(norms[rows, best])
    bad = ~(nrm > 0)
    vec[bad] = (1.0, 0.0, 0.0)  # an isotropic neighbourhood: no direction is preferred
    nrm[bad] = 1.0
    return np.asarray(vec / nrm[:, None], dtype=np.float64)
