"""Simulated elbow joints of seed 000 (Table 1, joints a-h) as surface point clouds.

A joint is the tube of :mod:`lrms.elbow.model`: a start leg, a bend of radius ``A`` through the
joint degree ``d`` and an end leg, swept by a circle of diameter ``D`` (legs of a flanged joint
have the flange diameter ``Df``). Points sit on a regular grid like the seed's: ``n_along``
stations spaced evenly along the centre line, and one point per ``step_deg`` of tube angle
around the pipe. With the defaults (131 stations, 1 deg, 360 deg coverage) a joint has 47,160
points, the seed's count; 90, 180 and 270 deg coverage give 11,790, 23,580 and 35,370.

Coverage is the arc of tube angle that is sampled, centred on ``view_deg``; the tube angle is
measured around the pipe from the bend's outward in-plane direction towards the model ``+Y``
(the bend-plane normal), so the default ``view_deg = 90`` is the half a scanner above the bend
plane sees.

Noise: ``noise`` (m) is added independently to each coordinate, either Gaussian with standard
deviation ``noise`` or uniform on ``[-noise, +noise]`` (the seed's "+-N mm" read both ways).

Table 1 reading: the seed's Flange column is a merged cell: joints a-f have none, g and h have
flanges. The seed's Tables 3-6 label the same eight joints a, b, c, e, f, g, h, i (see
``SEED_TABLE_LABELS``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from lrms.elbow.model import ElbowParams, rotation_matrix
from lrms.errors import LrmsError

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class JointSpec:
    """One row of the seed's Table 1."""

    name: str
    degree_deg: float
    ratio: float  # A / D
    flange: bool


TABLE1: dict[str, JointSpec] = {
    "a": JointSpec("a", 90.0, 1.0, False),
    "b": JointSpec("b", 90.0, 1.5, False),
    "c": JointSpec("c", 90.0, 0.5, False),
    "d": JointSpec("d", 45.0, 1.0, False),
    "e": JointSpec("e", 45.0, 1.5, False),
    "f": JointSpec("f", 45.0, 0.5, False),
    "g": JointSpec("g", 90.0, 1.0, True),
    "h": JointSpec("h", 45.0, 1.0, True),
}

#: Row label in the seed's Tables 3-6 -> joint of Table 1 (same type, degree and ratio order).
SEED_TABLE_LABELS: dict[str, str] = {"a": "a", "b": "b", "c": "c", "e": "d", "f": "e", "g": "f", "h": "g", "i": "h"}

#: Default flange diameter and flange length, in units of D.
FLANGE_DIAMETER = 1.5
FLANGE_LENGTH = 0.3
#: Default leg lengths (start, end) in units of D; unequal so that the two legs can be told apart.
LEGS = (0.6, 0.4)


@dataclass(frozen=True)
class SimJoint:
    """A simulated cloud with its true parameters."""

    points: FloatArray
    truth: ElbowParams
    portion: NDArray[np.int64]  # 0 start leg, 1 bend, 2 end leg, 3 bracket
    spec: JointSpec


def random_pose(rng: np.random.Generator, extent: float = 5.0) -> tuple[FloatArray, FloatArray]:
    """A random centre within ``extent`` m of the origin and a random rotation (psi kept off +-90 deg)."""
    center = rng.uniform(-extent, extent, 3)
    omega = rng.uniform(-math.pi, math.pi)
    psi = rng.uniform(-1.2, 1.2)
    kappa = rng.uniform(-math.pi, math.pi)
    return center, rotation_matrix(omega, psi, kappa)


def _centre_line(
    s: FloatArray, a: float, d: float, l1: float, l2: float
) -> tuple[FloatArray, FloatArray, NDArray[np.int64]]:
    """Centre point, outward in-plane normal and portion for arc-length ``s`` from the start leg's end."""
    theta0 = math.pi / 2 + d
    c = np.zeros((s.size, 3))
    nrm = np.zeros((s.size, 3))
    part = np.ones(s.size, dtype=np.int64)
    leg1 = s < l1
    bend_end = l1 + a * d
    leg2 = s > bend_end
    bend = ~(leg1 | leg2)
    # start leg: from (l1, 0, A) to (0, 0, A)
    c[leg1, 0] = l1 - s[leg1]
    c[leg1, 2] = a
    nrm[leg1, 2] = 1.0
    part[leg1] = 0
    th = math.pi / 2 + (s[bend] - l1) / a if a > 0 else np.full(int(bend.sum()), math.pi / 2)
    c[bend, 0] = a * np.cos(th)
    c[bend, 2] = a * np.sin(th)
    nrm[bend, 0] = np.cos(th)
    nrm[bend, 2] = np.sin(th)
    t = s[leg2] - bend_end
    c[leg2, 0] = a * math.cos(theta0) - t * math.sin(theta0)
    c[leg2, 2] = a * math.sin(theta0) + t * math.cos(theta0)
    nrm[leg2, 0] = math.cos(theta0)
    nrm[leg2, 2] = math.sin(theta0)
    part[leg2] = 2
    return c, nrm, part


def _add_noise(points: FloatArray, noise: float, kind: str, rng: np.random.Generator) -> FloatArray:
    if noise < 0:
        raise LrmsError(f"noise must be >= 0, got {noise}")
    if noise == 0:
        return points
    if kind == "gauss":
        return points + rng.normal(0.0, noise, points.shape)
    if kind == "uniform":
        return points + rng.uniform(-noise, noise, points.shape)
    raise LrmsError(f"noise kind must be 'gauss' or 'uniform', got {kind!r}")


def make_joint(
    spec: JointSpec | str,
    *,
    D: float = 0.1,
    center: FloatArray | None = None,
    rot: FloatArray | None = None,
    coverage_deg: float = 360.0,
    view_deg: float = 90.0,
    n_along: int = 131,
    step_deg: float = 1.0,
    noise: float = 0.0,
    noise_kind: str = "gauss",
    legs: tuple[float, float] | None = None,
    flange_diameter: float = FLANGE_DIAMETER,
    rng: np.random.Generator | None = None,
) -> SimJoint:
    """Simulate one joint of Table 1 (or any :class:`JointSpec`).

    ``legs``: start and end leg lengths in units of ``D`` (flanged joints: the flanges; default
    ``LEGS``, or ``FLANGE_LENGTH`` for flanges). ``(0, 0)`` gives the bare bend of Eq. 1-4.
    ``center``/``rot``: the pose (default: origin, identity).
    """
    if isinstance(spec, str):
        if spec not in TABLE1:
            raise LrmsError(f"unknown joint {spec!r}; Table 1 has {', '.join(TABLE1)}")
        spec = TABLE1[spec]
    if not 0 < coverage_deg <= 360:
        raise LrmsError(f"coverage must be in (0, 360] deg, got {coverage_deg}")
    if D <= 0 or n_along < 2 or step_deg <= 0:
        raise LrmsError("D, n_along and step_deg must be positive (n_along >= 2)")
    rng = np.random.default_rng() if rng is None else rng
    d = math.radians(spec.degree_deg)
    a = spec.ratio * D
    if legs is None:
        legs = (FLANGE_LENGTH, FLANGE_LENGTH) if spec.flange else LEGS
    l1, l2 = legs[0] * D, legs[1] * D
    total = l1 + a * d + l2
    s = (np.arange(n_along) + 0.5) * total / n_along
    c, nrm, part = _centre_line(s, a, d, l1, l2)
    n_around = round(coverage_deg / step_deg)
    phi = np.radians(view_deg - coverage_deg / 2 + (np.arange(n_around) + 0.5) * step_deg)
    radius = np.where(part == 1, D / 2, (flange_diameter if spec.flange else 1.0) * D / 2)
    ey = np.array([0.0, 1.0, 0.0])
    pts = c[:, None, :] + radius[:, None, None] * (
        np.cos(phi)[None, :, None] * nrm[:, None, :] + np.sin(phi)[None, :, None] * ey
    )
    pts = pts.reshape(-1, 3)
    portion = np.repeat(part, n_around)
    center = np.zeros(3) if center is None else np.asarray(center, dtype=np.float64)
    rot = np.eye(3) if rot is None else np.asarray(rot, dtype=np.float64)
    truth = ElbowParams(center, rot, a, D, d, flange_diameter * D if spec.flange else None)
    world = _add_noise(truth.to_world(pts), noise, noise_kind, rng)
    return SimJoint(world, truth, portion, spec)


def add_bracket(
    joint: SimJoint,
    *,
    theta_deg: float | None = None,
    band_width: float = 0.25,
    band_thickness: float = 0.08,
    rod_diameter: float = 0.3,
    rod_length: float = 0.5,
    coverage_deg: float = 180.0,
    view_deg: float = 90.0,
    spacing: float = 0.01,
    noise: float = 0.0,
    rng: np.random.Generator | None = None,
) -> SimJoint:
    """Add a mounting bracket on the bend: a clamp band around the tube and a support rod.

    The band (width ``band_width`` D, standing ``band_thickness`` D off the pipe) wraps the tube at
    bend angle ``theta_deg`` (default mid-bend); the rod (diameter ``rod_diameter`` D, length
    ``rod_length`` D) leaves the band radially outward in the bend plane. Sizes are in units of
    ``D``; ``spacing`` is the point spacing in units of ``D``. Only the arc of ``coverage_deg``
    around ``view_deg`` (as for the joint) is sampled on the band, and the rod's side facing +Y.
    """
    rng = np.random.default_rng() if rng is None else rng
    p = joint.truth
    D = p.D
    a = p.A
    th = p.degree / 2 + math.pi / 2 if theta_deg is None else math.radians(theta_deg)
    r_band = D / 2 + band_thickness * D
    step = spacing * D
    # band: torus patch of tube radius r_band over an arc length band_width*D of the centre line
    n_s = max(2, round(band_width * D / step))
    n_p = max(2, round(math.radians(coverage_deg) * r_band / step))
    ths = th + (np.arange(n_s) - (n_s - 1) / 2) * step / a
    phis = np.radians(view_deg - coverage_deg / 2) + (np.arange(n_p) + 0.5) * math.radians(coverage_deg) / n_p
    tt, pp = np.meshgrid(ths, phis, indexing="ij")
    rho = a + r_band * np.cos(pp)
    band = np.stack([rho * np.cos(tt), r_band * np.sin(pp), rho * np.sin(tt)], axis=-1).reshape(-1, 3)
    # rod: cylinder of radius rb along the outward direction u from the band
    rb = rod_diameter * D / 2
    u = np.array([math.cos(th), 0.0, math.sin(th)])
    v = np.array([-math.sin(th), 0.0, math.cos(th)])
    ey = np.array([0.0, 1.0, 0.0])
    n_l = max(2, round(rod_length * D / step))
    n_c = max(2, round(math.pi * rb / step))
    ts = a + r_band + (np.arange(n_l) + 0.5) * rod_length * D / n_l
    ang = (np.arange(n_c) + 0.5) * math.pi / n_c  # the half facing +Y
    t2, a2 = np.meshgrid(ts, ang, indexing="ij")
    rod = (t2[..., None] * u + rb * np.cos(a2)[..., None] * v + rb * np.sin(a2)[..., None] * ey).reshape(-1, 3)
    extra = _add_noise(p.to_world(np.vstack([band, rod])), noise, "gauss", rng)
    pts = np.vstack([joint.points, extra])
    portion = np.concatenate([joint.portion, np.full(extra.shape[0], 3, dtype=np.int64)])
    return SimJoint(pts, p, portion, joint.spec)
