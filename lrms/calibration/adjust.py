"""The adjustment: rig parameters jointly with the planes' and spheres' own parameters.

Unknowns: the free rig parameters (:class:`~lrms.kinematics.RigModel`), per plane a unit normal
(two local angles) and offset, per sphere a centre and radius. Observations: every beam on a
surface gives the signed distance of its point (the rig model applied to its raw ``(l, alpha,
beta, omega)``) from its surface, divided by that distance's standard deviation
``sqrt(g^T Sigma g)`` (``Sigma``: the point's covariance from the raw readings, Eq. 7 of seed
003 via :func:`lrms.covariance.point_covariances`; ``g``: the surface normal there). A sphere's
radius has a prior observation (its calibrated diameter), a sphere bar's length one more. The
sum of squares is minimised by Gauss-Newton with Levenberg-Marquardt damping on the normal
equations (the Jacobian is sparse: every beam touches the rig and one surface; the normal matrix
is small). Rig-parameter derivatives are central differences of the vectorised model.

Several rig poses (``which`` and ``poses``): every sweep after the first has its own rigid pose
(rotation about the world axes, multiplied onto its current rotation, and translation: six
unknowns between the rig's and the surfaces'); every beam's ray is placed in the world by its
own sweep's pose, so a beam row has six pose columns, its own sweep's (none for the first sweep,
whose rig frame is the world). Pose derivatives are central differences too: nudging every
pose's k-th parameter at once gives every beam's derivative by its own pose.

Identifiability: the normal matrix is reduced to the rig parameters (surfaces eliminated by the
Schur complement), its columns are scaled by each parameter's tolerance spread (:data:`SPREAD`:
30 mm, 1000 ppm, 5 mm, 0.3 deg, ...), and while its smallest eigenvalue is below
:data:`MIN_EIGENVALUE` (the data leave that direction's standard deviation above a tenth of the
spread) the parameter that takes most part in that direction (by :data:`HOLD_ORDER` among those
with at least a third of the largest share) is held at its nominal value.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy import sparse
from scipy.spatial.transform import Rotation

from lrms.calibration.data import Artefact, CalibrationError, DetectionError, DistanceSpec, Observations
from lrms.calibration.detect import PlaneSeg, SphereSeg
from lrms.calibration.optics import limb_echo
from lrms.covariance import NoiseModel
from lrms.kinematics import RigModel

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]

_DEG = float(np.deg2rad(1.0))
#: Tolerance spread of each parameter (SI): what a rig off the shelf may be off by.
SPREAD = {
    "k0": 0.03, "k1": 1e-3, "p": 5e-3, "q": 5e-3, "tilt_x": 0.3 * _DEG, "tilt_y": 0.3 * _DEG,
    "alpha_zero": 0.3 * _DEG, "beta_zero": 0.3 * _DEG, "beta_scale": 1e-3, "backlash": 0.3 * _DEG,
    "time_offset": 0.01,
}  # fmt: skip
#: Goals of issue 12 (SI): 0.3 mm for offsets and k0, 0.01 deg for tilts and zeros, 50 ppm for
#: scales; backlash like a zero; the time offset 1 ms (0.01 deg at 10 deg/s).
GOAL = {
    "k0": 0.3e-3, "k1": 50e-6, "p": 0.3e-3, "q": 0.3e-3, "tilt_x": 0.01 * _DEG, "tilt_y": 0.01 * _DEG,
    "alpha_zero": 0.01 * _DEG, "beta_zero": 0.01 * _DEG, "beta_scale": 50e-6, "backlash": 0.01 * _DEG,
    "time_offset": 1e-3,
}  # fmt: skip
#: Central-difference steps of the rig-parameter derivatives (SI).
_STEP = {
    "k0": 1e-4, "k1": 1e-5, "p": 1e-4, "q": 1e-4, "tilt_x": 1e-5, "tilt_y": 1e-5, "alpha_zero": 1e-5,
    "beta_zero": 1e-5, "beta_scale": 1e-5, "backlash": 1e-5, "time_offset": 1e-4,
}  # fmt: skip
#: Central-difference steps of the pose parameters: rotation (rad) about the world axes, translation (m).
_POSE_STEP = (1e-5, 1e-5, 1e-5, 1e-4, 1e-4, 1e-4)
#: Never determined by a cloud, whatever the data: held always.
STRUCTURAL = {
    "beta_zero": "a rotation of the whole cloud about the motor axis: not in the cloud's shape; it belongs to the "
    "rig's pose in the world (a levelled reference or a known target direction)",
    "tilt_y": "exactly a change of beta_zero plus the optical centre (p, q) turned about the shaft: never separable; "
    "its effect is carried by q (and p) and the rig's pose",
}
#: What data determine a parameter the given data could not.
ADVICE = {
    "k0": "planes seen at many incidence angles (a room: floor, walls, ceiling), or spheres of known diameter at "
    "more than one range",
    "k1": "a known length: sphere-bar centre distances (ASTM E3125 style), long and along the line of sight; "
    "sphere diameters alone are weak, planes alone never fix the scale",
    "p": "planes of several orientations around the rig (floor, walls, ceiling) over a wide motor sweep",
    "q": "planes of several orientations around the rig over a wide motor sweep",
    "tilt_x": "planes or spheres far along the motor axis and across it, seen over a wide motor sweep",
    "alpha_zero": "planes on both sides of the scan (floor and ceiling, or both side walls) over a wide motor sweep",
    "beta_scale": "planes seen over a wide range of motor angles (a sweep of 90 deg or more)",
    "backlash": "sweeps in both motor directions, with the motor speed of every beam (an MCAP raw log); with a "
    "time offset too, three different signed speeds (e.g. +10, -10, +20 deg/s)",
    "time_offset": "sweeps at different speeds in one direction (with backlash: three different signed speeds, "
    "e.g. +10, -10, +20 deg/s), with the motor speed of every beam (an MCAP raw log); only the difference between "
    "sweeps shows, a common angle is the motor zero",
}
#: Order in which parameters are held when the data cannot separate them (first = held first).
HOLD_ORDER = ("time_offset", "backlash", "k1", "beta_scale", "k0", "q", "tilt_x", "alpha_zero", "p")
#: Scaled eigenvalue below which a direction counts as undetermined (its std exceeds the tolerance spread:
#: the data say less than the tolerance already does).
MIN_EIGENVALUE = 1.0
#: Beams meeting a sphere at cos(incidence) below this are not used (silhouette: range and angle mix).
MIN_COS = 0.3
#: Re-segmentations at most (each under the estimate solved after the one before; the first under the
#: estimate from the nominal cloud's loose segmentation): a beam outside every surface's reach under a
#: rough estimate is taken back when the estimate improves (docs/calibration.md, "Calibration by
#: adjustment").
MAX_RESEGMENTATIONS = 4
#: The re-segmentation has settled when no surface's beam count grew by more than this (relative).
RESEGMENT_TOLERANCE = 0.005
#: A surface needs this many usable beams to stay in the adjustment.
MIN_SURFACE_BEAMS = 30
#: With a finite spot: a beam is censored when its spot, out to this many spot sigmas, is not wholly
#: on its own surface (the simulated LMS1xx's sub-rays reach 1.5 spot radii = 3 sigma). The kept
#: sphere beams' echo is the spot's light cut to this disc too (``limb_echo``'s ``extent_sigmas``:
#: ``BeamOptics.extent`` 1.5 at ``profile_sigma`` 0.25; the adjustment is not given the optics'
#: own extent yet, docs/calibration.md).
CENSOR_SIGMA = 3.0


@dataclass(frozen=True)
class AdjustOptions:
    max_iterations: int = 30
    outlier_sigma: float = 5.0
    max_plane_points: int = 20000
    seed: int = 0
    #: Re-segmentations at most (1: once, under the first estimate, as before issue 12's axis work).
    max_resegmentations: int = MAX_RESEGMENTATIONS

    def __post_init__(self) -> None:
        if self.max_resegmentations < 1:
            raise CalibrationError(f"max_resegmentations must be at least 1, got {self.max_resegmentations}")


@dataclass
class _Plane:
    index: IntArray
    normal: FloatArray
    offset: float
    basis: FloatArray  # (2, 3): the local directions of the normal's update

    @classmethod
    def make(cls, index: IntArray, normal: FloatArray, offset: float) -> _Plane:
        n = normal / np.linalg.norm(normal)
        return cls(index, n, offset, _basis(n))


@dataclass
class _Sphere:
    index: IntArray
    center: FloatArray
    radius: float
    artefact_index: int
    radius_known: float
    u_radius: float


def _distance(x: FloatArray, surf: _Plane | _Sphere) -> FloatArray:
    """Orthogonal distances of points ``(N, 3)`` from a surface."""
    if isinstance(surf, _Plane):
        return np.asarray(np.abs(x @ surf.normal - surf.offset), dtype=np.float64)
    return np.asarray(np.abs(np.linalg.norm(x - surf.center, axis=1) - surf.radius), dtype=np.float64)


def sphere_spot_bias(depth: FloatArray, radius: float, sigma: FloatArray, t: FloatArray) -> FloatArray:
    """How much longer the energy-weighted echo of a Gaussian spot (standard deviation ``sigma``)
    wholly on a sphere reads than its centre ray, whose chord half-depth is ``depth`` (``sqrt(R^2 -
    x0^2)``, ``x0`` the axis' distance from the centre), at range ``t``: to second order in ``sigma``,
    ``sigma^2 (3 depth^2 - R^2) / (2 depth^3) - 2 sigma^2 x0^2 / (depth^2 t)`` (``sigma^2 / R`` on
    the centre line). The adjustment uses the numerical quadrature
    (:func:`lrms.calibration.optics.limb_echo`) instead: toward the limb (``x0 -> R - 3 sigma``) the
    higher orders grow (with ``R`` = 0.2 m, ``sigma`` = 13 mm at 3 m: 0.5 mm off there).

    Derivation (docs/calibration.md): a sub-ray at ``(x0 + u, v)`` meets the sphere at ``t_ca -
    f(u, v)``, ``f = sqrt(R^2 - (x0 + u)^2 - v^2) ~ D - x0 u / D - R^2 u^2 / (2 D^3) - v^2 / (2 D)``;
    its energy ``~ cos(incidence) = f / R ~ (D - x0 u / D) / R``. Over the Gaussian (``E u^2 = E v^2 =
    sigma^2``) the mean of ``f`` is ``D - sigma^2 (R^2 / D^2 + 1) / (2 D)``, and the weight's
    correlation with the path adds ``-x0^2 sigma^2 / D^3``; with ``x0^2 = R^2 - D^2`` the range's
    shift is the first term; the energy's ``1 / t^2`` (``d ln w / du = -2 x0 / (D t)``) adds the second."""
    x0sq = radius**2 - depth**2
    return np.asarray(
        np.square(sigma) * ((3.0 * depth**2 - radius**2) / (2.0 * depth**3) - 2.0 * x0sq / (depth**2 * t)),
        dtype=np.float64,
    )


def resegment_settled(before: dict[str, int], after: dict[str, int], tolerance: float = RESEGMENT_TOLERANCE) -> bool:
    """Whether the re-segmentation has stopped taking beams back: the same surfaces as the round
    before (:meth:`Adjustment.resegment`), none gaining more than ``tolerance`` (relative). A round
    that only loses beams ends it too: re-segmenting further then drifts (measured: a spurious
    small "plane" of the detection slowly taking beams off two spheres, docs/calibration.md)."""
    if before.keys() != after.keys():
        return False
    return all(after[k] - n <= tolerance * max(n, 1) for k, n in before.items())


def _basis(n: FloatArray) -> FloatArray:
    a = np.eye(3)[int(np.argmin(np.abs(n)))]
    e1 = np.cross(n, a)
    e1 /= np.linalg.norm(e1)
    return np.stack([e1, np.cross(n, e1)])


@dataclass
class _State:
    rig: FloatArray  # full RigModel vector
    planes: list[_Plane]
    spheres: list[_Sphere]
    rot: FloatArray  # (P, 3, 3): world_from_rig rotation of each sweep's pose (pose 0: the identity, fixed)
    trans: FloatArray  # (P, 3): world_from_rig translation of each sweep's pose


def _rotation(rotvec: FloatArray) -> FloatArray:
    return np.asarray(Rotation.from_rotvec(rotvec).as_matrix(), dtype=np.float64)


class Adjustment:
    """One calibration adjustment over fixed observations and surface memberships."""

    def __init__(
        self,
        obs: Observations,
        planes: list[PlaneSeg],
        spheres: list[SphereSeg],
        artefact: Artefact,
        nominal: RigModel,
        noise: NoiseModel,
        options: AdjustOptions,
        which: IntArray | None = None,
        poses: Sequence[FloatArray] | None = None,
        spot: tuple[float, float] | None = None,
    ) -> None:
        """``which``: the sweep (pose) of every beam; ``poses``: the initial 4x4 world_from_rig of each
        sweep (the first is the world: the identity, held). Without them, one pose for all beams.
        ``spot``: the light spot's Gaussian sigma ``s0 + sd x range`` as ``(s0, sd)`` (m, rad); given,
        beams whose spot is not wholly on their surface are censored (:meth:`_censor_footprint`) and
        the sphere beams' expected range carries the spot's energy-weighted echo on the sphere (the
        ``limb_echo`` quadrature, :mod:`lrms.calibration.optics`; :func:`sphere_spot_bias` is only
        the closed form it is tested against); ``None``: the thin beam."""
        self.obs = obs
        self.spot = spot
        #: Per beam: how much longer its energy-weighted echo on its sphere reads than its centre
        #: ray (set by :meth:`_censor_footprint` for the kept sphere beams; 0 elsewhere).
        self._bias = np.zeros(len(obs))
        #: Beams censored for the footprint, by surface ("plane k", "sphere i" with the artefact's index).
        self.censored: dict[str, int] = {}
        self.which = np.zeros(len(obs), dtype=np.intp) if which is None else np.asarray(which, dtype=np.intp)
        if self.which.shape != (len(obs),):
            raise CalibrationError("one sweep index per observation")
        mats = [np.eye(4)] if poses is None else [np.asarray(t, dtype=np.float64) for t in poses]
        if not np.allclose(mats[0], np.eye(4)) or self.which.max(initial=0) >= len(mats):
            raise CalibrationError("the first sweep's pose is the world (the identity); one pose per sweep")
        self.n_poses = len(mats)
        self.artefact = artefact
        self.nominal = nominal
        self.noise = noise
        self.options = options
        rng = np.random.default_rng(options.seed)
        pl = []
        for seg in planes:
            pl.append(_Plane.make(self._cap(seg.index, rng), seg.normal, seg.offset))
        sp = []
        for ss in spheres:
            spec = artefact.spheres[ss.artefact_index]
            sp.append(_Sphere(ss.index, ss.center.copy(), ss.radius, ss.artefact_index, spec.diameter_m / 2,
                              spec.u_diameter_m / 2))  # fmt: skip
        self.state = _State(
            nominal.vector(), pl, sp, np.stack([m[:3, :3] for m in mats]), np.stack([m[:3, 3] for m in mats])
        )
        self.sphere_slot: dict[int, int] = {}
        self.distances: list[DistanceSpec] = []
        self._trim_silhouettes()
        self._sigma: list[FloatArray] = []
        self.free: list[str] = [n for n in RigModel.NAMES if n not in STRUCTURAL]
        #: Covariance of the pose parameters after :meth:`covariance` (6 per sweep after the first:
        #: rotation about the world axes in rad, then translation in m).
        self.pose_covariance: FloatArray = np.zeros((self.n_pose_params, self.n_pose_params))

    # -- geometry -------------------------------------------------------------------------
    @property
    def n_pose_params(self) -> int:
        """Unknowns of the poses: 6 per sweep after the first (rotation, translation)."""
        return 6 * (self.n_poses - 1)

    def _cap(self, idx: IntArray, rng: np.random.Generator) -> IntArray:
        """At most ``max_plane_points`` beams of a plane from each sweep's pose (a random subset)."""
        cap = self.options.max_plane_points
        if self.n_poses == 1:
            return idx if idx.size <= cap else np.sort(rng.choice(idx, cap, replace=False))
        parts = []
        for k in range(self.n_poses):
            own = idx[self.which[idx] == k]
            parts.append(own if own.size <= cap else rng.choice(own, cap, replace=False))
        return np.sort(np.concatenate(parts))

    def _world(self, st: _State, idx: IntArray, org: FloatArray, d: FloatArray | None = None) -> tuple[FloatArray, ...]:
        """Rig-frame points (or ray origins and directions) of beams ``idx`` in the world (their sweep's pose)."""
        if self.n_poses == 1:
            return (org,) if d is None else (org, d)
        w = self.which[idx]
        rot = st.rot[w]
        o = np.einsum("nij,nj->ni", rot, org) + st.trans[w]
        return (o,) if d is None else (o, np.einsum("nij,nj->ni", rot, d))

    def world_points(self, st: _State, idx: IntArray | None = None) -> FloatArray:
        """The beams mapped by the state's rig and placed by their sweep's pose."""
        o = self.obs
        i = np.arange(len(o)) if idx is None else idx
        x = RigModel.from_vector(st.rig).forward(o.l[i], o.alpha[i], o.beta[i], o.omega[i])
        return self._world(st, i, x)[0]

    def _nudged(self, st: _State, k: int, h: float) -> _State:
        """The state with every pose after the first moved by ``h`` along pose parameter ``k`` (each
        beam depends on its own sweep's pose only, so one nudge gives every beam's derivative)."""
        rot, trans = st.rot.copy(), st.trans.copy()
        if k < 3:
            rot[1:] = np.einsum("ij,njk->nik", _rotation(h * np.eye(3)[k]), rot[1:])
        else:
            trans[1:, k - 3] += h
        return _State(st.rig, st.planes, st.spheres, rot, trans)

    def _los(
        self, vec: FloatArray, idx: IntArray, surf: _Plane | _Sphere, st: _State | None = None
    ) -> tuple[FloatArray, ...]:
        """Residuals in the raw range reading: the reported range minus the range the rig model
        predicts for a beam meeting the surface, ``l - (t - k0) / (1 + k1)`` (so rescaling the
        cloud cannot shrink them). Also ``t``, ``cos(incidence)``, the beam directions and origins.
        Near grazing incidence ``cos`` is held at :data:`MIN_COS` / 2 (such beams are not used).
        Rays are placed in the world by their sweep's pose in ``st`` (default: the current state)."""
        o = self.obs
        m = RigModel.from_vector(vec)
        org, d = self._world(self.state if st is None else st, idx, *m.rays(o.alpha[idx], o.beta[idx], o.omega[idx]))
        if isinstance(surf, _Plane):
            nd = d @ surf.normal
            cos = np.abs(nd)
            nd = np.where(cos < MIN_COS / 2, np.copysign(MIN_COS / 2, nd), nd)
            t = (surf.offset - org @ surf.normal) / nd
        else:
            w = surf.center - org
            a = np.einsum("ij,ij->i", d, w)
            disc = surf.radius**2 - (np.einsum("ij,ij->i", w, w) - a * a)
            s = np.sqrt(np.maximum(disc, (MIN_COS / 2 * surf.radius) ** 2))
            t = a - s
            cos = s / surf.radius
            if self.spot is not None:
                t = t + self._bias[idx]
        return o.l[idx] - (t - m.k0) / (1.0 + m.k1), t, cos, d, org

    def _surface_residuals(
        self, st: _State, vec: FloatArray, names: list[str], poses: bool = True
    ) -> list[tuple[FloatArray, ...]]:
        """Per surface: residuals (N,), d(res)/d(surface params) (N,k), d(res)/d(rig) (N,F), and each
        residual's standard deviation under the noise model (N,): the range noise plus the lateral
        noise (``l sigma_alpha``, ``(l sin(alpha) + p) sigma_beta``) times ``tan(incidence)``; and
        d(res)/d(the beam's own pose) (N, 6; zero for the first sweep; no columns with one pose or
        ``poses=False``)."""
        o = self.obs
        scale = 1.0 + vec[RigModel.NAMES.index("k1")]
        out: list[tuple[FloatArray, ...]] = []
        surfaces: list[_Plane | _Sphere] = [*st.planes, *st.spheres]
        for surf in surfaces:
            idx = surf.index
            res, t, cos, d, org = self._los(vec, idx, surf, st)
            jr = np.empty((idx.size, len(names)))
            for k, name in enumerate(names):
                j = RigModel.NAMES.index(name)
                up, dn = vec.copy(), vec.copy()
                up[j] += _STEP[name]
                dn[j] -= _STEP[name]
                jr[:, k] = (self._los(up, idx, surf, st)[0] - self._los(dn, idx, surf, st)[0]) / (2 * _STEP[name])
            jp = np.zeros((idx.size, 6 if self.n_poses > 1 and poses else 0))
            for k in range(jp.shape[1]):
                h = _POSE_STEP[k]
                up_s, dn_s = self._nudged(st, k, h), self._nudged(st, k, -h)
                jp[:, k] = (self._los(vec, idx, surf, up_s)[0] - self._los(vec, idx, surf, dn_s)[0]) / (2 * h)
            jp[self.which[idx] == 0] = 0.0
            if isinstance(surf, _Plane):
                nd = d @ surf.normal
                nd = np.where(np.abs(nd) < MIN_COS / 2, np.copysign(MIN_COS / 2, nd), nd)
                x = org + t[:, None] * d  # t = (D - n.o) / (n.d): dt/du = -e1.x / (n.d), dt/dD = 1 / (n.d)
                js = np.column_stack([x @ surf.basis[0], x @ surf.basis[1], -np.ones(idx.size)]) / (nd * scale)[:, None]
            else:
                w = surf.center - org
                a = np.einsum("ij,ij->i", d, w)
                s = cos * surf.radius  # t = a - s: dt/dc = d + (w - a d) / s, dt/dr = -r / s
                js = -np.column_stack([d + (w - a[:, None] * d) / s[:, None], -surf.radius / s]) / scale
            tan2 = np.maximum(1.0 - cos**2, 0.0) / cos**2
            lateral = (o.l[idx] * self.noise.sigma_alpha) ** 2 + (
                (o.l[idx] * np.sin(o.alpha[idx]) + self.nominal.p) * self.noise.sigma_beta
            ) ** 2
            out.append((res, js, jr, np.sqrt(self.noise.sigma_l**2 + tan2 * lateral), jp))
        return out

    def _init_sigma(self) -> None:
        """Each residual's standard deviation from the raw readings' noise (Eq. 5 of seed 003)."""
        surf = self._surface_residuals(self.state, self.state.rig, [], poses=False)
        self._sigma = [t[3] for t in surf]

    # -- normal equations -----------------------------------------------------------------
    def _system(self, st: _State, names: list[str]) -> tuple[FloatArray, sparse.csr_matrix, list[FloatArray]]:
        """Weighted residuals, the sparse Jacobian over (rig names, poses after the first, planes,
        spheres), metric residuals. A beam's pose columns are its own sweep's six (none for the first)."""
        nr = len(names)
        npose = self.n_pose_params
        surf = self._surface_residuals(st, st.rig, names)
        rows: list[IntArray] = []
        cols: list[IntArray] = []
        vals: list[FloatArray] = []
        res_all: list[FloatArray] = []
        metric: list[FloatArray] = []
        row0 = 0
        col = nr + npose
        n_pl = len(st.planes)
        surfaces: list[_Plane | _Sphere] = [*st.planes, *st.spheres]
        for (res, js, jr, _, jp), sig, sf in zip(surf, self._sigma, surfaces, strict=True):
            n = res.size
            w = 1.0 / sig
            r_idx = np.arange(row0, row0 + n)
            block = np.hstack([jr * w[:, None], jp * w[:, None], js * w[:, None]])
            width = js.shape[1]
            c_idx = np.tile(np.r_[np.arange(nr), np.zeros(jp.shape[1], np.intp), np.arange(col, col + width)], (n, 1))
            if jp.shape[1]:  # the beam's own pose: columns nr + 6 (sweep - 1) + k (sweep 0: zeros, any column)
                c_idx[:, nr : nr + 6] = nr + 6 * np.maximum(self.which[sf.index] - 1, 0)[:, None] + np.arange(6)
            rows.append(np.repeat(r_idx, block.shape[1]))
            cols.append(c_idx.ravel())
            vals.append(block.ravel())
            res_all.append(res * w)
            metric.append(res)
            row0 += n
            col += width
        n_unknown = col
        sphere_col0 = nr + npose + 3 * n_pl
        # priors: the spheres' calibrated radii
        for k, sp in enumerate(st.spheres):
            rows.append(np.array([row0]))
            cols.append(np.array([sphere_col0 + 4 * k + 3]))
            vals.append(np.array([1.0 / sp.u_radius]))
            res_all.append(np.array([(sp.radius - sp.radius_known) / sp.u_radius]))
            row0 += 1
        # sphere-bar lengths
        for d in self.distances:
            a, b = st.spheres[self.sphere_slot[d.a]], st.spheres[self.sphere_slot[d.b]]
            v = a.center - b.center
            dist = float(np.linalg.norm(v))
            u = v / dist / d.u_distance_m
            ca = sphere_col0 + 4 * self.sphere_slot[d.a]
            cb = sphere_col0 + 4 * self.sphere_slot[d.b]
            rows.append(np.full(6, row0))
            cols.append(np.r_[np.arange(ca, ca + 3), np.arange(cb, cb + 3)])
            vals.append(np.r_[u, -u])
            res_all.append(np.array([(dist - d.distance_m) / d.u_distance_m]))
            row0 += 1
        jac = sparse.csr_matrix(
            (np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(row0, n_unknown)
        )
        return np.concatenate(res_all), jac, metric

    def _apply(self, st: _State, names: list[str], delta: FloatArray) -> _State:
        rig = st.rig.copy()
        for k, name in enumerate(names):
            rig[RigModel.NAMES.index(name)] += delta[k]
        col = len(names)
        rot, trans = st.rot.copy(), st.trans.copy()
        for k in range(1, self.n_poses):
            rot[k] = _rotation(delta[col : col + 3]) @ rot[k]
            trans[k] = trans[k] + delta[col + 3 : col + 6]
            col += 6
        planes = []
        for pl in st.planes:
            du, dv, dd = delta[col : col + 3]
            n = pl.normal + du * pl.basis[0] + dv * pl.basis[1]
            planes.append(_Plane.make(pl.index, n, pl.offset + dd))
            col += 3
        spheres = []
        for sp in st.spheres:
            c = sp.center + delta[col : col + 3]
            spheres.append(_Sphere(sp.index, c, sp.radius + delta[col + 3], sp.artefact_index, sp.radius_known,
                                   sp.u_radius))  # fmt: skip
            col += 4
        return _State(rig, planes, spheres, rot, trans)

    def solve(self, names: list[str]) -> tuple[FloatArray, sparse.csr_matrix, int]:
        """Levenberg-Marquardt from the current state; returns the final weighted residuals, Jacobian
        and iteration count."""
        lam = 1e-3
        r, jac, _ = self._system(self.state, names)
        cost = float(r @ r)
        it = 0
        for it in range(1, self.options.max_iterations + 1):  # noqa: B007
            cost2 = cost
            delta = np.zeros(jac.shape[1])
            nm = (jac.T @ jac).toarray()
            grad = jac.T @ r
            diag = np.clip(np.diag(nm), 1e-300, None)
            step_ok = False
            while lam < 1e12:
                try:
                    delta = np.linalg.solve(nm + lam * np.diag(diag), -grad)
                except np.linalg.LinAlgError:
                    lam *= 10
                    continue
                trial = self._apply(self.state, names, delta)
                r2, jac2, _ = self._system(trial, names)
                cost2 = float(r2 @ r2)
                if np.isfinite(cost2) and cost2 <= cost:
                    self.state, r, jac = trial, r2, jac2
                    lam = max(lam / 10, 1e-9)
                    step_ok = True
                    break
                lam *= 10
            done = not step_ok or (cost - cost2) <= 1e-10 * max(cost, 1.0) or float(
                np.max(np.abs(delta) * np.sqrt(diag))
            ) < 1e-6  # fmt: skip
            if step_ok:
                cost = cost2
            if done:
                break
        return r, jac, it

    def resegment(self, min_plane_points: int, max_sigma: float) -> dict[str, int]:
        """Give every beam to its nearest surface under the current estimate, keeping beams within
        ``max_sigma`` range-noise sigmas of it. A beam is dropped when the point where the model
        says it meets its surface (noise-free: a test on the measured point would select beams by
        their noise and bias the range) lies within that reach of a second surface (corners,
        edges). A plane that only gathered the bends of a miscalibrated cloud loses its points and
        is dropped; planes are subsampled again, grazing beams and silhouettes left out.

        Returns the beams given to each surface ("plane k" in the order kept, "sphere i" with the
        artefact's index), before the planes' subsampling and the silhouette trim: what
        :func:`resegment_settled` compares between rounds."""
        x = self.world_points(self.state)
        reach = max_sigma * self.noise.sigma_l
        live = list(self.state.planes)
        while True:
            surfaces: list[_Plane | _Sphere] = [*live, *self.state.spheres]
            d = np.stack([_distance(x, sf) for sf in surfaces])
            nearest = np.argmin(d, axis=0)
            ok = d[nearest, np.arange(x.shape[0])] <= reach
            for k, sf in enumerate(surfaces):  # corners and edges belong to neither surface
                idx = np.flatnonzero(ok & (nearest == k))
                _, t, _, dirs, org = self._los(self.state.rig, idx, sf)
                hit = org + t[:, None] * dirs
                others = [_distance(hit, other) for j, other in enumerate(surfaces) if j != k]
                if others:
                    ok[idx[np.min(np.stack(others), axis=0) <= reach]] = False
            counts = np.bincount(nearest[ok], minlength=d.shape[0])[: len(live)]
            if live and counts.min() < min_plane_points:
                live.pop(int(np.argmin(counts)))  # a plane of bends and bits: drop it, assign again
                continue
            break
        rng = np.random.default_rng(self.options.seed + 1)
        planes = []
        assigned: dict[str, int] = {}
        for k, pl in enumerate(live):
            idx = np.flatnonzero(ok & (nearest == k))
            assigned[f"plane {k}"] = int(idx.size)
            _, _, cos, _, _ = self._los(self.state.rig, idx, pl)
            planes.append(_Plane.make(self._cap(idx[cos >= MIN_COS], rng), pl.normal, pl.offset))
        for k, sp in enumerate(self.state.spheres):
            sp.index = np.flatnonzero(ok & (nearest == len(live) + k))
            assigned[f"sphere {sp.artefact_index}"] = int(sp.index.size)
        self.state = _State(self.state.rig, planes, self.state.spheres, self.state.rot, self.state.trans)
        self._trim_silhouettes()
        self._init_sigma()
        return assigned

    def surface_beams(self) -> dict[str, int]:
        """The beams each surface uses now ("plane k", "sphere i" with the artefact's index)."""
        out = {f"plane {k}": int(pl.index.size) for k, pl in enumerate(self.state.planes)}
        out.update({f"sphere {sp.artefact_index}": int(sp.index.size) for sp in self.state.spheres})
        return out

    def _trim_silhouettes(self) -> None:
        """Keep the beams that meet their surface at cos(incidence) >= :data:`MIN_COS` (grazing beams
        on planes, silhouettes of spheres: there range and angle errors mix non-linearly)."""
        surfaces: list[_Plane | _Sphere] = [*self.state.planes, *self.state.spheres]
        for surf in surfaces:
            _, _, cos, _, _ = self._los(self.state.rig, surf.index, surf)
            surf.index = surf.index[cos >= MIN_COS]
        if self.spot is not None:
            self._censor_footprint()
        self._drop_thin()

    def _censor_footprint(self) -> None:
        """Drop the beams whose spot (out to :data:`CENSOR_SIGMA` sigmas, ``sigma = s0 + sd t``) is
        not wholly on their own surface, under the current estimate: on a sphere, the beam axis
        further than ``R - k sigma`` from the centre (the limb: the echo is pulled toward the covered
        part); on a plane, the hit within ``k sigma / cos(incidence)`` of another plane (corners and
        edges: the spot's long axis on an inclined plane) or the spot touching a sphere in front
        of it (``lateral distance < R + k sigma``). The counts per surface go to :attr:`censored`."""
        assert self.spot is not None
        s0, sd = self.spot
        k = CENSOR_SIGMA
        self.censored = {}
        planes, spheres = self.state.planes, self.state.spheres
        for n, pl in enumerate(planes):
            _, t, cos, d, org = self._los(self.state.rig, pl.index, pl)
            sig = s0 + sd * np.maximum(t, 0.0)
            hit = org + t[:, None] * d
            bad = np.zeros(pl.index.size, dtype=bool)
            for other in planes:
                if other is not pl:
                    bad |= _distance(hit, other) < k * sig / np.maximum(cos, MIN_COS)
            for sp in spheres:
                w = sp.center - org
                tc = np.einsum("ij,ij->i", w, d)
                lateral = np.linalg.norm(w - tc[:, None] * d, axis=1)
                bad |= (tc < t) & (lateral < sp.radius + k * (s0 + sd * np.maximum(tc, 0.0)))
            self.censored[f"plane {n}"] = int(bad.sum())
            pl.index = pl.index[~bad]
        for sp in spheres:
            self._bias[sp.index] = 0.0
            _, t, cos, _, _ = self._los(self.state.rig, sp.index, sp)
            depth = sp.radius * cos
            x0 = np.sqrt(np.maximum(sp.radius**2 - depth**2, 0.0))
            bad = x0 > sp.radius - k * (s0 + sd * t)
            self.censored[f"sphere {sp.artefact_index}"] = int(bad.sum())
            sp.index = sp.index[~bad]
            t_ca = (t + depth)[~bad]
            echo, _ = limb_echo(x0[~bad], t_ca, np.full(t_ca.size, sp.radius), s0 + sd * t_ca, k)
            self._bias[sp.index] = echo - (t_ca - depth[~bad])

    def _drop_thin(self) -> None:
        """Drop surfaces left with too few beams to carry their own parameters (and the sphere-bar
        lengths of dropped spheres)."""
        planes = [p for p in self.state.planes if p.index.size >= MIN_SURFACE_BEAMS]
        spheres = [s for s in self.state.spheres if s.index.size >= MIN_SURFACE_BEAMS]
        if not planes and not spheres:
            raise DetectionError(
                f"no surface keeps {MIN_SURFACE_BEAMS} usable beams (grazing beams and silhouettes are not used)"
            )
        self.state = _State(self.state.rig, planes, spheres, self.state.rot, self.state.trans)
        self.sphere_slot = {sp.artefact_index: k for k, sp in enumerate(spheres)}
        self.distances = [d for d in self.artefact.distances if d.a in self.sphere_slot and d.b in self.sphere_slot]

    def reject_outliers(self, names: list[str]) -> int:
        """Drop beams whose weighted residual exceeds ``outlier_sigma``; returns how many."""
        _, _, metric = self._system(self.state, names)
        dropped = 0
        kept_sigma = []
        surfaces: list[_Plane | _Sphere] = [*self.state.planes, *self.state.spheres]
        for surf, res, sig in zip(surfaces, metric, self._sigma, strict=True):
            keep = np.abs(res / sig) <= self.options.outlier_sigma
            dropped += int(np.count_nonzero(~keep))
            surf.index = surf.index[keep]
            kept_sigma.append(sig[keep])
        self._sigma = kept_sigma
        return dropped

    def scaled_reduced_normal(self, names: list[str]) -> FloatArray:
        """The rig block of the normal matrix with the surfaces eliminated, columns scaled by :data:`SPREAD`."""
        _, jac, _ = self._system(self.state, names)
        nm = (jac.T @ jac).toarray()
        nr = len(names)
        a, b, c = nm[:nr, :nr], nm[:nr, nr:], nm[nr:, nr:]
        red = a - b @ np.linalg.lstsq(c, b.T, rcond=None)[0] if c.size else a
        s = np.array([SPREAD[n] for n in names])
        return np.asarray(red * np.outer(s, s), dtype=np.float64)

    def choose_free(self) -> tuple[list[str], dict[str, str], FloatArray]:
        """The parameters the data determine, those held (with reasons) and the scaled eigenvalues."""
        names = list(self.free)
        held: dict[str, str] = {}
        first_eig: FloatArray | None = None
        while names:
            red = self.scaled_reduced_normal(names)
            w, v = np.linalg.eigh(red)
            if first_eig is None:
                first_eig = w
            if w[0] >= MIN_EIGENVALUE:
                break
            share = np.abs(v[:, 0])
            cand = [n for n, s in zip(names, share, strict=True) if s >= share.max() / 3]
            pick = min(cand, key=lambda n: HOLD_ORDER.index(n) if n in HOLD_ORDER else len(HOLD_ORDER))
            others = [n for n in cand if n != pick]
            std_spreads = 1 / np.sqrt(max(w[0], 1e-300))
            reason = (
                f"not determined by these data (a direction with std {std_spreads:.3g} x its tolerance spread"
                + (f", mixed with {', '.join(others)}" if others else "")
                + f"); held at nominal. Would be determined by: {ADVICE[pick]}"
            )
            held[pick] = reason
            names.remove(pick)
        return names, held, np.asarray(first_eig if first_eig is not None else np.zeros(0), dtype=np.float64)

    def covariance(self, names: list[str], jac: sparse.csr_matrix, r: FloatArray) -> tuple[FloatArray, float, int]:
        """Covariance of the free rig parameters (a priori, scaled by the variance factor when above
        1), the variance factor and the degrees of freedom."""
        nm = (jac.T @ jac).toarray()
        dof = jac.shape[0] - jac.shape[1]
        if dof <= 0:
            raise CalibrationError(f"too few observations for {jac.shape[1]} unknowns")
        s0sq = float(r @ r) / dof
        try:
            inv = np.linalg.inv(nm)
        except np.linalg.LinAlgError:
            raise CalibrationError("the normal matrix is singular after holding the undetermined parameters") from None
        nr = len(names)
        npose = self.n_pose_params
        self.pose_covariance = inv[nr : nr + npose, nr : nr + npose] * max(1.0, s0sq)
        return inv[:nr, :nr] * max(1.0, s0sq), s0sq, dof

    def surface_summary(
        self, names: list[str]
    ) -> tuple[list[tuple[str, tuple[float, ...], int, float, int]], FloatArray]:
        _, _, metric = self._system(self.state, names)
        rows = []
        for pl, res in zip(self.state.planes, metric, strict=False):
            rows.append(("plane", (*pl.normal.tolist(), pl.offset), res.size, float(np.sqrt(np.mean(res**2))), -1))
        for sp, res in zip(self.state.spheres, metric[len(self.state.planes) :], strict=True):
            rows.append(
                ("sphere", (*sp.center.tolist(), 2 * sp.radius), res.size, float(np.sqrt(np.mean(res**2))),
                 sp.artefact_index)
            )  # fmt: skip
        return rows, np.concatenate(metric)
