"""Detection: the cylinder RANSAC model, the support plane (table) and its height under the part,
a free plane RANSAC."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from lrms.cylinder.grid import nearest_in_grid
from lrms.cylinder.model import Cylinder, estimate_normals, knn_query, perpendicular_frame
from lrms.cylinder.options import DetectOptions
from lrms.cylinder.refine import CylinderFit, refine_cylinder
from lrms.errors import FitError
from lrms.ransac import PlaneModel, angle_gate_cosine, ransac

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]


class CylinderModel:
    """RANSAC model on rows ``(x, y, z, nx, ny, nz)``: a cylinder from 2 points with normals.

    ``normal_weight`` (m per rad) converts the angle between a point's normal and the model's
    radial direction into distance in the residual.
    """

    normal_weight = 0.02
    radius_range: tuple[float, float] = (0.005, 2.0)

    def __init__(self) -> None:
        self.cylinder: Cylinder | None = None

    def estimate(self, data: FloatArray) -> bool:
        d = np.asarray(data, dtype=np.float64)
        if d.shape[0] < 2 or d.shape[1] < 6:
            return False
        if d.shape[0] > 2:
            return self._estimate_many(d)
        p1, n1, p2, n2 = d[0, :3], d[0, 3:6], d[1, :3], d[1, 3:6]
        w = np.cross(n1, n2)
        sw = float(np.linalg.norm(w))
        if sw < 0.05:  # normals nearly parallel: axis undefined
            return False
        w = w / sw
        # closest points of the lines p1 + s n1 and p2 + t n2
        r12 = p1 - p2
        b = float(n1 @ n2)
        denom = 1.0 - b * b
        e, f = float(n1 @ r12), float(n2 @ r12)
        s = (b * f - e) / denom
        t = (f - b * e) / denom
        c = 0.5 * ((p1 + s * n1) + (p2 + t * n2))
        cyl_r = float(np.linalg.norm(Cylinder(c, w, 1.0).radial(p1)))
        lo, hi = self.radius_range
        if not (lo <= cyl_r <= hi):
            return False
        self.cylinder = Cylinder(c, w, cyl_r)
        return True

    def _estimate_many(self, d: FloatArray) -> bool:
        """Least-squares polish on many inliers (orthogonal distance), from a 2-point start."""
        if self.cylinder is None:
            # start from the best pair among a few
            best: Cylinder | None = None
            for i in range(1, min(d.shape[0], 8)):
                m = CylinderModel()
                if m.estimate(d[[0, i]]):
                    best = m.cylinder
                    break
            if best is None:
                return False
            self.cylinder = best
        try:
            fit = refine_cylinder(d[:, :3], self.cylinder, rays=None, sigma=1.0, max_rounds=1)
        except FitError:
            return False
        self.cylinder = fit.cylinder
        return True

    @classmethod
    def batch_hypotheses(cls, samples: FloatArray) -> tuple[FloatArray, NDArray[np.bool_]]:
        """:meth:`estimate` on ``(B, 2, 6)`` samples at once: rows ``(point, direction, radius)``."""
        p1, n1, p2, n2 = samples[:, 0, :3], samples[:, 0, 3:6], samples[:, 1, :3], samples[:, 1, 3:6]
        w = np.cross(n1, n2)
        sw = np.linalg.norm(w, axis=1)
        ok = sw >= 0.05  # normals nearly parallel: axis undefined
        w = w / np.where(ok, sw, 1.0)[:, None]
        r12 = p1 - p2
        b = np.einsum("bi,bi->b", n1, n2)
        denom = np.where(ok, 1.0 - b * b, 1.0)
        e, f = np.einsum("bi,bi->b", n1, r12), np.einsum("bi,bi->b", n2, r12)
        s = (b * f - e) / denom
        t = (f - b * e) / denom
        c = 0.5 * ((p1 + s[:, None] * n1) + (p2 + t[:, None] * n2))
        v = p1 - c
        rad = v - np.einsum("bi,bi->b", v, w)[:, None] * w
        r = np.linalg.norm(rad, axis=1)
        lo, hi = cls.radius_range
        ok &= (lo <= r) & (r <= hi) & np.all(np.isfinite(c), axis=1)
        return np.column_stack([c, w, r]), ok

    @classmethod
    def batch_residuals(cls, params: FloatArray, data: FloatArray) -> FloatArray:
        """:meth:`residuals` of ``B`` cylinders on ``(m, 6)`` rows as ``(B, m)`` products."""
        x = data[:, :3]
        c, w, r = params[:, 0:3], params[:, 3:6], params[:, 6]
        xw = w @ x.T - np.einsum("bi,bi->b", c, w)[:, None]  # (x - c).w
        xx = np.einsum("mi,mi->m", x, x)
        cx = c @ x.T
        d2 = xx[None, :] - 2.0 * cx + np.einsum("bi,bi->b", c, c)[:, None] - xw * xw
        dist = np.sqrt(np.maximum(d2, 0.0))
        res = np.abs(dist - r[:, None])
        if data.shape[1] >= 6:
            nrm = data[:, 3:6]
            # rad . n = (x - c).n - ((x - c).w) (w.n)
            rn = np.einsum("mi,mi->m", x, nrm)[None, :] - c @ nrm.T - xw * (w @ nrm.T)
            cosang = np.minimum(np.abs(rn) / np.maximum(dist, 1e-12), 1.0)
            res += cls.normal_weight * np.arccos(cosang)
        return np.asarray(res, dtype=np.float64)

    @classmethod
    def batch_inlier_residuals(cls, params: FloatArray, data: FloatArray, threshold: float) -> FloatArray:
        """:meth:`batch_residuals` where they can be below ``threshold``, ``inf`` elsewhere (the
        angle term only for rows whose distance alone is below it)."""
        x = data[:, :3]
        c, w, r = params[:, 0:3], params[:, 3:6], params[:, 6]
        xw = w @ x.T - np.einsum("bi,bi->b", c, w)[:, None]
        xx = np.einsum("mi,mi->m", x, x)
        d2 = xx[None, :] - 2.0 * (c @ x.T) + np.einsum("bi,bi->b", c, c)[:, None] - xw * xw
        dist = np.sqrt(np.maximum(d2, 0.0))
        res = np.abs(dist - r[:, None])
        if data.shape[1] >= 6:
            nrm = data[:, 3:6]
            # rad . n = (x - c).n - ((x - c).w) (w.n), by (B, 3) x (3, m) products; the arccos
            # only where it can matter: the distance below the threshold and the angle below
            # threshold / weight (|rad . n| above that angle's cosine times |rad|)
            rn = np.abs(np.einsum("mi,mi->m", x, nrm)[None, :] - c @ nrm.T - xw * (w @ nrm.T))
            rad = np.maximum(dist, 1e-12)
            near = (res < threshold) & (rn > angle_gate_cosine(threshold, cls.normal_weight) * rad)
            out = np.full(res.shape, np.inf)
            out[near] = res[near] + cls.normal_weight * np.arccos(np.minimum(rn[near] / rad[near], 1.0))
            return out
        return np.asarray(res, dtype=np.float64)

    @classmethod
    def from_params(cls, row: FloatArray) -> CylinderModel:
        model = cls()
        model.cylinder = Cylinder(row[0:3], row[3:6], float(row[6]))
        return model

    def residuals(self, data: FloatArray) -> FloatArray:
        if self.cylinder is None:
            raise FitError("model not estimated")
        d = np.asarray(data, dtype=np.float64)
        rad = self.cylinder.radial(d[:, :3])
        dist = np.linalg.norm(rad, axis=1)
        res = np.abs(dist - self.cylinder.radius)
        if d.shape[1] >= 6:
            cosang = np.abs(np.sum(rad * d[:, 3:6], axis=1)) / np.maximum(dist, 1e-12)
            res = res + self.normal_weight * np.arccos(np.clip(cosang, 0.0, 1.0))
        return np.asarray(res, dtype=np.float64)


def detect_plane(
    points: ArrayLike,
    threshold: float,
    rng: np.random.Generator,
    min_share: float = 0.05,
    normals: ArrayLike | None = None,
    normal_weight: float = 0.02,
) -> tuple[FloatArray, float, NDArray[np.bool_]] | None:
    """Dominant plane ``(normal, offset, inlier mask)`` of a cloud, or ``None`` if it holds less
    than ``min_share`` of the points. With ``normals``, a point counts only if its normal agrees
    with the plane's (see :class:`lrms.ransac.PlaneModel`)."""
    pts = np.asarray(points, dtype=np.float64)
    data = pts if normals is None else np.hstack([pts, np.asarray(normals, dtype=np.float64)])

    class _Plane(PlaneModel):
        pass

    _Plane.normal_weight = normal_weight if normals is not None else 0.0
    try:
        model, mask = ransac(data, _Plane, 3, threshold, max_trials=1500, min_trials=400, rng=rng, score_size=5000)
    except FitError:
        return None
    if np.count_nonzero(mask) < min_share * pts.shape[0]:
        return None
    return model.normal, model.offset, mask


#: Cell of the nearest-sample search of :meth:`Background.off`, in units of the threshold (the
#: nearest of all within that distance; 99.3 % agreed with a k-d tree's on an issue-15 cloud).
NEAREST_CELL = 2.0 / 3.0


@dataclass(frozen=True)
class Background:
    """The background planes found on a working sample of the cloud (:func:`background_planes`):
    ``planes`` ``(normal, offset)``, the sample's row indices ``sample`` into the cloud, their
    points, whether each was left by the planes (``left``) and their PCA normals."""

    planes: list[tuple[FloatArray, float]]
    sample: IntArray
    sample_points: FloatArray
    left: NDArray[np.bool_]
    normals: FloatArray

    def off(self, pts: FloatArray, rows: IntArray, threshold: float) -> IntArray:
        """Those of ``rows`` (indices into ``pts``) not set aside: a row is set aside when it lies
        within ``threshold`` of a plane and its nearest sampled point was taken by a plane (the
        nearest within the grid cells around it, :func:`~lrms.cylinder.grid.nearest_in_grid`,
        with cells of :data:`NEAREST_CELL` ``threshold``)."""
        if not self.planes:
            return rows
        p = pts[rows]
        near = np.zeros(rows.size, dtype=bool)
        for normal, offset in self.planes:
            near |= np.abs(p @ normal - offset) < threshold
        out = ~near
        if np.any(near):
            nn = nearest_in_grid(self.sample_points, p[near], NEAREST_CELL * threshold)
            out[near] = self.left[nn]
        return rows[out]


#: Candidate planes that fail the piece test (:func:`_plane_extent`) before any plane is taken
#: and are passed over; a later failure, or one after a plane was taken, ends the search.
PIECE_SKIPS = 2

#: Smallest cell (m) of the occupancy grid in which a background plane's points must form one
#: piece (:func:`_plane_extent`; the cell grows with the plane's sampled point spacing).
WALL_CELL = 0.1
#: Cell of that grid in units of the plane's sampled point spacing (the median distance of its
#: points to their :data:`SPACING_NEIGHBOUR`-th nearest one in the plane, about ``1/sqrt(density)``
#: for a random sample): about 6 points a cell, so a random sample of an extended surface is one
#: piece at any sampling density, while holes of a few spacings (between objects) still separate.
CELL_PER_SPACING = 2.5
#: The neighbour whose distance is the point spacing (the 1st is along a scan line where the
#: sample is dense: too short for the distance between lines).
SPACING_NEIGHBOUR = 3


def plane_cell(uv: FloatArray) -> float:
    """Cell (m) of the piece test for a plane's points ``uv`` (``(n, 2)``, in the plane):
    :data:`CELL_PER_SPACING` times their median :data:`SPACING_NEIGHBOUR`-th neighbour distance,
    at least :data:`WALL_CELL`."""
    n = uv.shape[0]
    if n < 2:
        return WALL_CELL
    k = min(SPACING_NEIGHBOUR, n - 1)
    nb = knn_query(uv)(uv, k + 1)[:, k]
    spacing = float(np.median(np.linalg.norm(uv[nb] - uv, axis=1)))
    return max(WALL_CELL, CELL_PER_SPACING * spacing)


@dataclass(frozen=True)
class _Piece:
    """The largest connected piece of a plane's points in its cell grid (:func:`_plane_piece`):
    the in-plane frame ``frame`` (2 x 3), the grid's origin and cell, the piece's cells as sorted
    keys, and ``extent``, the smaller span (2nd-98th percentiles) of its points."""

    frame: FloatArray
    origin: FloatArray
    cell: float
    width: int
    keys: NDArray[np.int64]
    extent: float

    def _key(self, points: FloatArray) -> NDArray[np.int64]:
        c = np.floor((points @ self.frame.T - self.origin) / self.cell).astype(np.int64)
        return np.asarray(c[:, 0] * self.width + c[:, 1], dtype=np.int64)

    def covers(self, points: FloatArray) -> NDArray[np.bool_]:
        """Whether each point (``(m, 3)``) falls in a cell of the piece."""
        key = self._key(points)
        pos = np.minimum(np.searchsorted(self.keys, key), self.keys.size - 1)
        return np.asarray(self.keys[pos] == key, dtype=bool)


def _plane_piece(on: FloatArray, normal: FloatArray) -> _Piece:
    """The largest connected piece of a plane's points ``on`` (8-connected cells of
    :func:`plane_cell` in the plane). A wall, floor or table top is one extended piece; the front
    strip of a cylinder together with a few unrelated objects that happen to lie in the same plane
    is not (on the whole room cloud one such "plane" took a third of the part's points in 2 of 6
    runs before this test).

    The cell scales with the plane's own sampled spacing, so whether a wall is one piece does not
    depend on how densely the working sample covers it: with fixed 0.1 m cells the back wall of a
    room sweep at 6 m (sampled about every 0.15 m, 4 % of the cloud) came out as 0.48-1.7 m
    pieces depending on the draw, and was missed when below ``wall_min_extent``. A dense strip
    (the part's front, 20-40 mm spacing) keeps 0.1 m cells."""
    e1, e2 = perpendicular_frame(normal)
    frame = np.stack([e1, e2])
    uv = on @ frame.T
    origin = uv.min(axis=0)
    cell = plane_cell(uv)
    cells = np.floor((uv - origin) / cell).astype(np.int64)
    lab = _cell_components(cells)
    big = lab == int(np.argmax(np.bincount(lab)))
    span = np.ptp(np.percentile(uv[big], [2.0, 98.0], axis=0), axis=0)
    width = int(cells[:, 1].max()) + 3
    keys = np.unique(cells[big, 0] * width + cells[big, 1])
    return _Piece(frame, origin, cell, width, keys, float(np.min(span)))


def _plane_extent(on: FloatArray, normal: FloatArray) -> float:
    """The smaller span (2nd-98th percentiles) of the largest connected piece of a plane's points
    (:func:`_plane_piece`)."""
    return _plane_piece(on, normal).extent


def _cell_components(cells: NDArray[np.int64]) -> IntArray:
    """The 8-connected component of each point's cell (non-negative integer ``(n, 2)`` cells),
    numbered by the component's first cell in raster order (as ``scipy.ndimage.label`` numbers
    them, less one). Numpy only, on the occupied cells: edges to the four forward neighbours,
    then minimum-label hooking with pointer jumping (importing scipy.ndimage was a tenth of a
    second or more of ``lrms fit``'s start)."""
    width = int(cells[:, 1].max()) + 3
    key = cells[:, 0] * width + cells[:, 1] + 1
    keys, of_point = np.unique(key, return_inverse=True)
    m = keys.size
    us, vs = [], []
    for off in (1, width - 1, width, width + 1):  # right, and the three cells of the next row
        pos = np.searchsorted(keys, keys + off)
        hit = pos < m
        hit[hit] = keys[pos[hit]] == keys[hit] + off
        us.append(np.flatnonzero(hit))
        vs.append(pos[hit])
    u, v = np.concatenate(us), np.concatenate(vs)
    lab = np.arange(m)
    while u.size:
        lu, lv = lab[u], lab[v]
        if np.array_equal(lu, lv):
            break
        low = np.minimum(lu, lv)
        np.minimum.at(lab, lu, low)  # hook each root onto the smaller label across an edge
        np.minimum.at(lab, lv, low)
        while True:  # pointer jumping until every cell points at its root
            nxt = lab[lab]
            if np.array_equal(nxt, lab):
                break
            lab = nxt
    _, comp = np.unique(lab, return_inverse=True)
    return np.asarray(comp[of_point.ravel()], dtype=np.intp)


#: Take into a background plane the sampled points within ``threshold`` of it that lie in its
#: piece's cells (:func:`_plane_piece`) though their normals disagree with it.
ABSORB_IN_PIECE = True

#: Rows of the working sample on which each background plane RANSAC scores its hypotheses.
PLANE_SCORE_SIZE = 1000
#: Rows of the RANSAC's sample on which the cylinder RANSAC scores its hypotheses (None: all).
CYLINDER_SCORE_SIZE: int | None = 1000


def background_planes(
    points: ArrayLike, options: DetectOptions | None = None, rng: np.random.Generator | None = None
) -> Background:
    """The large planes of a cloud (walls, floor, ceiling, table tops), found on a random sample
    of at most ``options.wall_sample`` points (see :func:`dominant_planes`)."""
    opt = options if options is not None else DetectOptions()
    g = rng if rng is not None else np.random.default_rng(0)
    pts = np.asarray(points, dtype=np.float64)
    n = pts.shape[0]
    if opt.max_planes <= 0 or n < 3 * max(opt.min_inliers, 10):
        return Background([], np.arange(0), np.zeros((0, 3)), np.zeros(0, dtype=bool), np.zeros((0, 3)))
    idx = np.sort(g.choice(n, size=opt.wall_sample, replace=False)) if n > opt.wall_sample else np.arange(n)
    data = np.hstack([pts[idx], estimate_normals(pts[idx], opt.normal_k)])

    class _Plane(PlaneModel):
        normal_weight = opt.threshold / float(np.deg2rad(30.0))

    left = np.ones(idx.size, dtype=bool)
    pool = np.ones(idx.size, dtype=bool)  # rows the next plane RANSAC draws from
    planes: list[tuple[FloatArray, float]] = []
    skipped = 0
    for _ in range(opt.max_planes):
        rows = np.flatnonzero(pool)
        if rows.size < 3 * opt.min_inliers:
            break
        try:
            model, mask = ransac(
                data[rows],
                _Plane,
                3,
                opt.threshold,
                max_trials=500,
                min_trials=100,
                rng=g,
                score_size=PLANE_SCORE_SIZE,
                batch=50,
            )
        except FitError:
            break
        if np.count_nonzero(mask) < opt.wall_min_share * idx.size:
            break
        piece = _plane_piece(pts[idx[rows[mask]]], model.normal)
        if piece.extent < opt.wall_min_extent:
            if planes or skipped >= PIECE_SKIPS:
                break
            # not one extended piece (the part's front strip with a few points in line with it,
            # which outnumbered a grazing table's in some sweeps): not a plane, but the table may
            # be among the rest
            skipped += 1
            pool[rows[mask]] = False
            continue
        planes.append((np.asarray(model.normal, dtype=np.float64), float(model.offset)))
        taken = rows[mask]
        if ABSORB_IN_PIECE:
            # sampled points on the plane inside its piece whose own normals missed the plane's
            # (neighbourhoods of a sparse sample straddle corners): the plane's too, else each
            # lends its "left" to the cloud's points nearest it (:meth:`Background.off`)
            rest = rows[~mask]
            on_plane = rest[np.abs(pts[idx[rest]] @ model.normal - model.offset) < opt.threshold]
            taken = np.concatenate([taken, on_plane[piece.covers(pts[idx[on_plane]])]])
        left[taken] = False
        pool[taken] = False
    return Background(planes, idx, pts[idx], left, data[:, 3:6])


def dominant_planes(
    points: ArrayLike, options: DetectOptions | None = None, rng: np.random.Generator | None = None
) -> tuple[IntArray, list[tuple[FloatArray, float]]]:
    """Set aside the large planes of a cloud (walls, floor, ceiling, table tops) before the cylinder
    RANSAC; returns the indices of the points off them and the planes ``(normal, offset)``.

    Works on a random sample of at most ``options.wall_sample`` points (the RANSAC draws from a few
    thousand anyway): normals by PCA of ``normal_k`` neighbours, then up to ``max_planes`` plane
    RANSACs, each on the points left by the previous ones, a point counting for a plane when it
    lies within ``threshold`` of it and its normal is within about 30 deg of the plane's. A plane
    is taken only if it holds at least ``wall_min_share`` of the sample and its points span at
    least ``wall_min_extent`` in both directions of the plane (2nd-98th percentiles); the first
    plane that fails ends the search. This protects the part: a cylinder of D >= 0.1 m is not a
    plane at the scanner's noise, and its points whose normals agree with one plane form a strip
    ``D sin(30 deg)`` wide at most, far narrower than ``wall_min_extent``. A point of the whole
    cloud is set aside when it lies within ``threshold`` of a taken plane and its nearest sampled
    point was taken by a plane (:meth:`Background.off`; :func:`fit_cylinder` classifies only the
    points its RANSAC draws).
    """
    opt = options if options is not None else DetectOptions()
    pts = np.asarray(points, dtype=np.float64)
    bg = background_planes(pts, opt, rng)
    return bg.off(pts, np.arange(pts.shape[0]), opt.threshold), bg.planes


def candidate_pool(
    pts: FloatArray, bg: Background, opt: DetectOptions, rng: np.random.Generator, size: int
) -> IntArray:
    """At least ``size`` random indices of points off the background planes (all of them when
    there are fewer): a random draw, classified by :meth:`Background.off`, grown until enough."""
    n = pts.shape[0]
    if not bg.planes:
        return np.arange(n)
    share = max(float(np.mean(bg.left)) if bg.left.size else 1.0, 0.05)
    order = rng.permutation(n)
    got: list[IntArray] = []
    have, start = 0, 0
    while have < size and start < n:
        take = int(min(n - start, max(1.5 * (size - have) / share, 1000)))
        rows = np.sort(order[start : start + take])
        start += take
        kept = bg.off(pts, rows, opt.threshold)
        got.append(kept)
        have += kept.size
    return np.sort(np.concatenate(got)) if got else np.arange(0)


def detect_cylinder(
    points: ArrayLike,
    options: DetectOptions | None = None,
    rng: np.random.Generator | None = None,
    candidates: ArrayLike | None = None,
    normals: ArrayLike | None = None,
) -> tuple[Cylinder, tuple[FloatArray, float] | None]:
    """Rough cylinder (RANSAC, 2 points + normals) and the table plane if one was found.

    ``candidates``: indices of the points the RANSAC draws from (e.g. those off the background
    planes, :func:`dominant_planes`); the table plane is searched among all points. ``normals``:
    the candidates' normals when already known (one row per candidate, e.g. the background
    sample's, :class:`Background`); else PCA normals of the RANSAC's sample."""
    opt = options if options is not None else DetectOptions()
    g = rng if rng is not None else np.random.default_rng(0)
    pts = np.asarray(points, dtype=np.float64)
    n = pts.shape[0]
    if n < opt.min_inliers:
        raise FitError(f"too few points to detect a cylinder: {n} (need {opt.min_inliers})")
    pool = pts if candidates is None else pts[np.asarray(candidates)]
    if pool.shape[0] < opt.min_inliers:
        raise FitError(f"too few points off the background planes to detect a cylinder: {pool.shape[0]}")
    m = pool.shape[0]
    pick = g.choice(m, size=opt.sample_size, replace=False) if m > opt.sample_size else np.arange(m)
    sub = pool[pick]
    if normals is not None:
        nrm = np.asarray(normals, dtype=np.float64)
        if nrm.shape != (m, 3):
            raise FitError(f"normals must have one row per candidate, got {nrm.shape} for {m}")
        data = np.hstack([sub, nrm[pick]])
    else:
        data = np.hstack([sub, estimate_normals(sub, opt.normal_k)])

    # a footprint widens the apparent part (``opt.spot``, :meth:`DetectOptions.widening`)
    spot_r = opt.widening(float(np.max(np.linalg.norm(sub, axis=1))))

    class _Model(CylinderModel):
        normal_weight = opt.normal_weight
        radius_range = (opt.radius_range[0], opt.radius_range[1] + spot_r)

    min_inl = max(opt.min_inliers // 2, int(0.02 * data.shape[0]), 6)
    model, _ = ransac(
        data,
        _Model,
        2,
        opt.threshold,
        max_trials=opt.max_trials,
        min_trials=opt.min_trials,
        min_inliers=min_inl,
        refine=False,
        rng=g,
        score_size=CYLINDER_SCORE_SIZE,
        batch=50,
    )
    assert model.cylinder is not None
    return model.cylinder, support_plane(pts, model.cylinder, opt)


def support_plane(pts: FloatArray, cyl: Cylinder, opt: DetectOptions) -> tuple[FloatArray, float] | None:
    """The plane the part stands on: perpendicular to the axis (within 10 deg), the most
    populated such slab among the points off the cylinder, refined by total least squares.

    (A free plane RANSAC is unreliable here: at the rig's grazing view of a table the points
    come in sparse scan lines, so their neighbourhood normals are ill-defined, and the front of
    the part is as flat as the table within the range noise.)
    """
    dist = np.abs(cyl.surface_distance(pts))
    off = pts[dist > opt.threshold]
    if off.shape[0] < max(opt.min_inliers, opt.plane_min_share * pts.shape[0]):
        return None
    s = off @ cyl.direction
    width = opt.plane_threshold
    edges = np.arange(s.min(), s.max() + 2 * width, width)
    if edges.size < 2:
        return None
    counts, edges = np.histogram(s, bins=edges)
    # the part stands on the plane: a slab through the middle of the points on the candidate is
    # not its support (a dense band of the part's own points, left off a wrong candidate, can
    # outnumber the table), so only slabs beyond the 5th / 95th percentile of the candidate's
    # points along the axis, less two slab widths, are eligible
    s_on = pts[dist <= opt.threshold] @ cyl.direction
    if s_on.size >= opt.min_inliers:
        lo, hi = np.percentile(s_on, [5.0, 95.0])
        mid = 0.5 * (edges[:-1] + edges[1:])
        counts = np.where((mid <= lo + 2 * width) | (mid >= hi - 2 * width), counts, 0)
    pair = counts[:-1] + counts[1:] if counts.size > 1 else counts
    if not np.any(pair > 0):
        return None
    i = int(np.argmax(pair))
    centre = edges[i + 1] if counts.size > 1 else 0.5 * (edges[0] + edges[1])
    near = off[np.abs(s - centre) < width]
    if near.shape[0] < max(opt.min_inliers, opt.plane_min_share * pts.shape[0]):
        return None
    model = PlaneModel()
    for _ in range(2):
        if not model.estimate(near):
            return None
        near = off[model.residuals(off) < width]
        if near.shape[0] < 3:
            return None
    if abs(float(model.normal @ cyl.direction)) < np.cos(np.deg2rad(10.0)):
        return None
    return model.normal, model.offset


def table_height(
    pts: FloatArray, fit: CylinderFit, plane: tuple[FloatArray, float], opt: DetectOptions
) -> tuple[FloatArray, float, FloatArray] | None:
    """The table under the fitted part as a plane perpendicular to the fitted axis.

    Returns ``(up, height, origin)``: the axis direction pointing from the table to the part and
    the table's height along it, measured from ``origin`` (the fitted axis point), or ``None``
    when the support plane is not under the part or too few table points lie near the part. The
    height is the mode (2 mm bins, then the mean within 3 mm) of the axial coordinates of the
    points off the part within 0.3 m of its surface and 50 mm of the support plane: the part
    stands on the table, so the table's normal is the axis, and the few points near the part
    fix its height better than the plane fitted to the whole grazing table (tilted by 1-4 deg
    in some sweeps).
    """
    cyl = fit.cylinder
    pn, po = plane
    up = cyl.direction
    denom = float(pn @ up)
    if abs(denom) < 0.9:
        return None
    s = (pts - cyl.point) @ up
    s0 = (po - float(pn @ cyl.point)) / denom
    if s0 > float(np.median(s[fit.inliers])):
        up, s, s0 = -up, -s, -s0
    dist = cyl.axis_distance(pts)
    near = (dist > cyl.radius + opt.threshold) & (dist < cyl.radius + 0.3) & (np.abs(s - s0) < 0.05)
    if np.count_nonzero(near) < opt.min_inliers:
        return None
    counts, edges = np.histogram(s[near], bins=np.arange(s0 - 0.05, s0 + 0.0501, 0.002))
    mode = 0.5 * (edges[int(np.argmax(counts))] + edges[int(np.argmax(counts)) + 1])
    for _ in range(2):
        sel = near & (np.abs(s - mode) < 0.003)
        if np.count_nonzero(sel) < opt.min_inliers:
            return None
        mode = float(np.median(s[sel]))
    return np.asarray(up, dtype=np.float64), float(np.mean(s[sel])), cyl.point


#: Bin width (m) along the axis of the inlier density that locates the part's top.
TOP_BIN = 0.02


def _top_height(h_cand: FloatArray, h_inl: FloatArray) -> float:
    """Height of the part's top end above the table, from the predicted hit heights of its
    beams: the upper edge (plus one bin) of the last :data:`TOP_BIN` bin holding at least a fifth
    of the median count of the fit's inliers per bin. Above it the candidates are beams that
    pass over the part and meet the model's infinite extension: clutter, never the part. A part
    whose top is not in view keeps its dense bins to the end, and nothing is cut."""
    top = float(np.max(h_cand))
    edges = np.arange(0.0, top + TOP_BIN, TOP_BIN)
    if edges.size < 4:
        return top
    counts, _ = np.histogram(h_inl, bins=edges)
    filled = counts[counts > 0]
    if filled.size == 0:
        return top
    dense = np.flatnonzero(counts >= 0.2 * float(np.median(filled)))
    return min(top, float(edges[dense[-1] + 1]) + TOP_BIN)
