"""A realistic LMS1xx: finite beam footprint, echo formation, RSSI, range systematics, noise.

Each beam is a cone of light, sampled by a fixed pattern of sub-rays: the spot is
``exit_diameter + divergence x range`` wide (SICK LMS1xx operating instructions 8012471, section
3.6.2: 8 mm at the front screen plus 15 mrad x range, about 45 mm at 2.5 m) with a Gaussian
profile. Every sub-ray is ray-cast exactly; the sub-rays of one beam are grouped into echoes by
range (a gap wider than ``echo_separation_m`` starts a new echo: a depth step inside the spot
gives two pulses), and each echo gets the energy of its sub-rays (profile weight x remission x
|cos incidence| / range^2). An echo is detected when its energy share of the spot reaches
``edge_threshold`` (a partly hit spot returns less energy: manual 3.6.3) and its energy the
sensitivity limit (18 m at 10 % remission: LMS1xx data sheets). The reported range is the
energy-weighted range of the echo's sub-rays (mixed pixels: "the output follows the energy
distribution", manual 3.6.3) or its leading edge (``range_mode``), plus range systematics and
noise. Up to two echoes per beam are kept (DIST1/DIST2 with RSSI1/RSSI2, manual 3.8.4).

Everything is vectorized: beams are processed in chunks of ``chunk_rays`` sub-rays, the sub-ray
hits of a chunk are one :meth:`Scene.raycast`, and the echoes are formed with sorting and
``bincount`` over the ``(beams, sub_rays)`` arrays of chunks of at most 2^16 sub-rays (bounded
memory; the same result as one piece). The parameters SICK does not publish (edge
threshold, echo separation, the forms of the systematic terms) are ours and say so; see
``docs/sensor-model.md``.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from sim.scene.scene import Scene
from sim.scene.sensor import (
    SIGMA_ALPHA_SEED003,
    SIGMA_BETA_SEED003,
    Echoes,
    Sensor,
    SensorModel,
    gaussian_angle_noise,
)
from sim.scene.shapes import FloatArray, SceneError

#: LMS1xx light spot at the front screen (m): operating instructions 8012471, section 3.6.2.
LMS1XX_EXIT_DIAMETER = 0.008
#: LMS1xx beam divergence (rad, full angle: the spot grows by 15 mm per metre), ibid.
LMS1XX_DIVERGENCE = 0.015
#: Statistical range error, typical and maximum (1 sigma, m): SICK "Measurement errors LMSxxx".
LMS1XX_SIGMA_TYPICAL = 0.012
LMS1XX_SIGMA_MAX = 0.020
#: Range 18 m on a 10 % remission target (LMS1xx data sheets): the weakest detectable full-spot
#: echo, in units of a white target filling the spot head-on at 1 m (remission x cos / range^2).
LMS1XX_MIN_ENERGY = 0.10 / 18.0**2
#: SICK's systematic-error bound (typical, max; m): SICK "Measurement errors LMSxxx".
LMS1XX_SYSTEMATIC_TYPICAL = 0.030
LMS1XX_SYSTEMATIC_MAX = 0.040

RangeMode = Literal["weighted", "first"]
EchoFilter = Literal["first", "last"]
_GOLDEN_ANGLE = float(np.pi * (3.0 - np.sqrt(5.0)))
#: Sub-rays per chunk of echo formation (at most ``chunk_rays``): about 30 working arrays of 0.5 MB
#: each, reused by the allocator from chunk to chunk (few fresh pages: little system time).
_ECHO_CHUNK_RAYS = 1 << 16
#: Entries per sub-ray up to which a chunk's (echo, object) energy table is dense (:func:`_main_object`).
_DENSE_OBJECT_TABLE = 4


def _check(name: str, value: float, lo: float = 0.0, hi: float = np.inf, lo_open: bool = False) -> None:
    v = float(value)
    bad = not np.isfinite(v) or v > hi or (v <= lo if lo_open else v < lo)
    if bad:
        bound = f"{'>' if lo_open else '>='} {lo:g}" + (f" and <= {hi:g}" if np.isfinite(hi) else "")
        raise SceneError(f"LMS1xx sensor {name} must be finite and {bound}, got {value!r}")


@dataclass(frozen=True)
class Footprint:
    """The beam's light spot and its sub-ray sampling.

    Spot diameter at range r: ``exit_diameter_m + divergence_rad * r`` (SICK 8012471, 3.6.2). We
    read that diameter as the Gaussian's 1/e^2 intensity diameter: ``profile_sigma`` = sigma /
    diameter = 0.25 (our reading; SICK does not define the edge). ``extent``: the sub-rays cover
    a disc of ``extent`` spot radii (1.5: 98.9 % of a Gaussian's energy at profile_sigma 0.25).
    ``sub_rays`` (even): a point-symmetric sunflower pattern whose radii are the Gaussian's
    equal-energy quantiles (sub-ray i of m = K/2 at the radius enclosing (i + 1/2)/m of the truncated
    profile's energy, golden-angle azimuths, each mirrored through the centre), so each sub-ray
    carries the weight 1/K of the profile; every line through the spot's centre splits them in
    half. For a straight edge across the spot this follows the continuous profile's covered energy
    within 0.07 (K = 32), 0.04 (64), 0.03 (128) (max over edge offsets and orientations; about half
    that of equal-area sub-rays weighted by the profile).

    ``rotation_rad``: the whole pattern turned about the beam by this angle (0: as above). A
    pattern's sampling error at a limb is the same in every sweep cast with it; a noiseless fit of
    seed 003's part moves by about +-0.5 mm from pattern to pattern (docs/sensor-model.md, "One
    pattern per run"), so a coverage run draws its sweeps from several turned patterns
    (``bench_sensor_model --patterns``) to average that offset.
    """

    exit_diameter_m: float = LMS1XX_EXIT_DIAMETER
    divergence_rad: float = LMS1XX_DIVERGENCE
    profile_sigma: float = 0.25
    extent: float = 1.5
    sub_rays: int = 128
    rotation_rad: float = 0.0

    def __post_init__(self) -> None:
        _check("exit_diameter_m", self.exit_diameter_m, hi=1.0)
        _check("divergence_rad", self.divergence_rad, hi=0.5)
        _check("profile_sigma", self.profile_sigma, lo_open=True, hi=10.0)
        _check("extent", self.extent, lo_open=True, hi=10.0)
        if not isinstance(self.sub_rays, int | np.integer) or self.sub_rays < 2 or self.sub_rays % 2:
            raise SceneError(f"LMS1xx sensor sub_rays must be an even integer >= 2, got {self.sub_rays!r}")
        _check("rotation_rad", self.rotation_rad, lo=-2.0 * np.pi, hi=2.0 * np.pi)

    def diameter(self, range_m: FloatArray | float) -> FloatArray:
        """Nominal spot diameter (m) at ``range_m``."""
        return np.asarray(self.exit_diameter_m + self.divergence_rad * np.asarray(range_m, dtype=np.float64))

    def pattern(self) -> tuple[FloatArray, FloatArray, FloatArray]:
        """Sub-ray positions ``(a, b)`` in spot radii across the beam, and their weights (sum 1)."""
        m = self.sub_rays // 2
        i = np.arange(m, dtype=np.float64)
        s = 2.0 * self.profile_sigma  # the Gaussian's sigma in spot radii
        inside = 1.0 - np.exp(-0.5 * (self.extent / s) ** 2)  # energy share within the extent
        rho = s * np.sqrt(-2.0 * np.log(1.0 - (i + 0.5) / m * inside))  # equal-energy rings
        phi = i * _GOLDEN_ANGLE + self.rotation_rad
        a = np.concatenate([rho * np.cos(phi), -rho * np.cos(phi)])
        b = np.concatenate([rho * np.sin(phi), -rho * np.sin(phi)])
        return a, b, np.full(2 * m, 1.0 / (2 * m))

    def sub_rays_of(self, origins: FloatArray, dirs: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Origins and unit directions ``(N, K, 3)`` of the sub-rays of ``N`` beams.

        Sub-ray k starts ``(a_k u + b_k v) * exit_diameter / 2`` off the beam's origin and leans
        out by ``(a_k, b_k) * divergence / 2``, so it meets a plane across the beam at range r
        ``(a_k, b_k)`` spot radii from the axis (u, v: unit vectors across the beam).
        """
        a, b, _ = self.pattern()
        d = np.asarray(dirs, dtype=np.float64)
        helper = np.zeros_like(d)
        use_x = np.abs(d[:, 2]) > 0.9
        helper[~use_x, 2] = 1.0
        helper[use_x, 0] = 1.0
        u = np.cross(d, helper)
        u /= np.linalg.norm(u, axis=1, keepdims=True)
        v = np.cross(d, u)
        off = a[None, :, None] * u[:, None, :] + b[None, :, None] * v[:, None, :]
        o = np.asarray(origins, dtype=np.float64)[:, None, :] + off * (0.5 * self.exit_diameter_m)
        sd = d[:, None, :] + off * np.tan(0.5 * self.divergence_rad)
        sd /= np.linalg.norm(sd, axis=2, keepdims=True)
        return o, sd


@dataclass(frozen=True)
class RangeSystematics:
    """Systematic range error, added to every echo's range (all terms 0 by default).

    ``r + scale * r + offset_m + walk_m_per_decade * log10(1 / energy)
    + incidence_m * (1 - cos) + temperature_coeff_m_per_k * (temperature_c - reference_temperature_c)
    + warmup_m * exp(-t_on / warmup_tau_s)``. SICK bounds the sum at +-30 mm typical, +-40 mm max
    (``LMS1XX_SYSTEMATIC_*``) and says it depends on temperature; it publishes no forms. These
    forms are our models: a constant offset and a scale error (Ye & Borenstein 2002, Pomerleau
    et al. 2012); amplitude walk of a leading-edge timer, longer for weaker echoes (so remission,
    incidence and range through the echo energy, relative to a white target head-on at 1 m); an
    incidence term; a linear temperature term; a warm-up drift decaying with the time since
    power-on (``t_on``; real-rig.md: about 1 cm over tens of minutes, to be verified).
    """

    offset_m: float = 0.0
    scale: float = 0.0
    walk_m_per_decade: float = 0.0
    incidence_m: float = 0.0
    temperature_coeff_m_per_k: float = 0.0
    temperature_c: float = 25.0
    reference_temperature_c: float = 25.0
    warmup_m: float = 0.0
    warmup_tau_s: float = 600.0

    def __post_init__(self) -> None:
        for name in ("offset_m", "scale", "walk_m_per_decade", "incidence_m", "temperature_coeff_m_per_k", "warmup_m"):
            v = float(getattr(self, name))
            if not np.isfinite(v) or abs(v) > 1.0:
                raise SceneError(f"LMS1xx systematic {name} must be finite and within +-1, got {v!r}")
        for name in ("temperature_c", "reference_temperature_c"):
            _check(name, getattr(self, name), lo=-273.15, hi=1000.0)
        _check("warmup_tau_s", self.warmup_tau_s, lo_open=True)

    def apply(
        self, range_m: FloatArray, energy: FloatArray, cos_incidence: FloatArray, time_s: FloatArray | None
    ) -> FloatArray:
        """Ranges with the systematic error added (``time_s`` None: warmed up)."""
        out = range_m * (1.0 + self.scale) + self.offset_m
        out = out + self.temperature_coeff_m_per_k * (self.temperature_c - self.reference_temperature_c)
        if self.walk_m_per_decade:
            out = out + self.walk_m_per_decade * -np.log10(np.maximum(energy, 1e-12))
        if self.incidence_m:
            out = out + self.incidence_m * (1.0 - cos_incidence)
        if self.warmup_m and time_s is not None:
            out = out + self.warmup_m * np.exp(-np.maximum(time_s, 0.0) / self.warmup_tau_s)
        return np.asarray(out, dtype=np.float64)


@dataclass(frozen=True)
class LMS1xxSensor:
    """The LMS1xx with a finite footprint (see the module notes and docs/sensor-model.md).

    Echo formation: ``edge_threshold``: an echo is detected when its share of the spot's energy
    profile reaches this fraction of a full-spot return from the same surface (SICK does not
    publish it; 0.3 is our middle guess, the benches vary 0.1..0.5); ``min_energy``: the weakest
    detectable echo (remission x cos / range^2 summed over the spot: 18 m at 10 %);
    ``range_mode``: "weighted" (energy-weighted range over the echo's sub-rays: mixed pixels) or
    "first" (first hit: the range at which the echo's accumulated share of the spot, sub-rays in
    range order, reaches ``edge_threshold``: the leading edge seen by a threshold discriminator;
    its nearest sub-ray for a threshold of 0); ``echo_separation_m``: sub-ray ranges further apart than this
    form separate echoes (our estimate of the pulse-pair resolution; SICK publishes none);
    ``echo_filter``: DIST1 carries the "first" or the "last" echo (SICK's FREchoFilter 0 / 2);
    DIST2 the second echo (filter "first") or the first (filter "last") when there are two.

    Noise: ``sigma = sqrt(sigma_typical^2 + (sigma_max^2 - sigma_typical^2) * min(1,
    min_energy / energy) + (spread_noise * s)^2)`` with ``s`` the energy-weighted spread of the
    echo's sub-ray ranges (pulse stretching on inclined surfaces): 12 mm on strong echoes, 20 mm
    at the sensitivity limit (SICK's typical / max statistical error). Angle noise: seed 003's.

    RSSI digits: ``rssi_gain * sum(weight * remission * cos) * min(1, rssi_reference_m /
    range)^rssi_range_exponent`` (our model: flat while the receiver saturates, then falling).
    """

    footprint: Footprint = field(default_factory=Footprint)
    systematics: RangeSystematics = field(default_factory=RangeSystematics)
    edge_threshold: float = 0.3
    min_energy: float = LMS1XX_MIN_ENERGY
    range_mode: RangeMode = "weighted"
    echo_separation_m: float = 0.6
    echo_filter: EchoFilter = "first"
    sigma_typical: float = LMS1XX_SIGMA_TYPICAL
    sigma_max: float = LMS1XX_SIGMA_MAX
    spread_noise: float = 0.5
    sigma_alpha: float = SIGMA_ALPHA_SEED003
    sigma_beta: float = SIGMA_BETA_SEED003
    range_min: float = 0.5
    range_max: float = 20.0
    quantum: float = 0.0
    rssi_gain: float = 200.0
    rssi_reference_m: float = 2.0
    rssi_range_exponent: float = 2.0
    chunk_rays: int = 1 << 18

    def __post_init__(self) -> None:
        if not isinstance(self.footprint, Footprint) or not isinstance(self.systematics, RangeSystematics):
            raise SceneError("LMS1xx sensor footprint / systematics must be Footprint / RangeSystematics")
        _check("edge_threshold", self.edge_threshold, hi=1.0)
        _check("min_energy", self.min_energy)
        _check("echo_separation_m", self.echo_separation_m, lo_open=True, hi=100.0)
        for name in ("sigma_typical", "sigma_alpha", "sigma_beta", "spread_noise", "quantum", "rssi_gain"):
            _check(name, getattr(self, name))
        _check("sigma_max", self.sigma_max, lo=self.sigma_typical)
        _check("rssi_reference_m", self.rssi_reference_m, lo_open=True)
        _check("rssi_range_exponent", self.rssi_range_exponent, hi=10.0)
        if self.range_mode not in ("weighted", "first"):
            raise SceneError(f"LMS1xx sensor range_mode must be 'weighted' or 'first', got {self.range_mode!r}")
        if self.echo_filter not in ("first", "last"):
            raise SceneError(f"LMS1xx sensor echo_filter must be 'first' or 'last', got {self.echo_filter!r}")
        if not (0 <= self.range_min < self.range_max) or not np.isfinite(self.range_max):
            raise SceneError(f"sensor range limits must satisfy 0 <= min < max, got {self.range_min}, {self.range_max}")
        if self.chunk_rays < self.footprint.sub_rays:
            raise SceneError("LMS1xx sensor chunk_rays must hold at least one beam's sub-rays")

    # ------------------------------------------------------------------ Sensor protocol
    def angle_noise(self, shape: tuple[int, ...], rng: np.random.Generator | None) -> tuple[FloatArray, FloatArray]:
        """Draws of (d_alpha, d_beta) for ``shape`` samples (zeros without ``rng``)."""
        return gaussian_angle_noise(self.sigma_alpha, self.sigma_beta, shape, rng)

    def echoes(
        self,
        scene: Scene,
        origins: FloatArray,
        dirs: FloatArray,
        rng: np.random.Generator | None,
        time_s: FloatArray | None = None,
    ) -> Echoes:
        """The echoes of ``N`` beams (origins and unit directions ``(N, 3)``); see the class notes."""
        return self.form_echoes(self.cast_footprints(scene, origins, dirs), rng, time_s)

    # ------------------------------------------------------------------ the two stages
    def cast_footprints(self, scene: Scene, origins: FloatArray, dirs: FloatArray) -> SubRayHits:
        """Ray-cast every beam's sub-rays (the geometric, noise-free stage; reusable)."""
        o = np.asarray(origins, dtype=np.float64)
        d = np.asarray(dirs, dtype=np.float64)
        if o.ndim != 2 or o.shape[1] != 3 or d.shape != o.shape:
            raise SceneError(f"origins and dirs must both have shape (N, 3), got {o.shape} and {d.shape}")
        k = self.footprint.sub_rays
        n = o.shape[0]
        t = np.empty((n, k))
        idx = np.empty((n, k), dtype=np.intp)
        cos = np.empty((n, k))
        rem = np.empty((n, k))
        step = max(1, self.chunk_rays // k)
        for lo in range(0, n, step):
            hi = min(n, lo + step)
            so, sd = self.footprint.sub_rays_of(o[lo:hi], d[lo:hi])
            hits = scene.raycast(so.reshape(-1, 3), sd.reshape(-1, 3))
            t[lo:hi] = hits.range.reshape(-1, k)
            idx[lo:hi] = hits.index.reshape(-1, k)
            cos[lo:hi] = hits.cos_incidence.reshape(-1, k)
            rem[lo:hi] = hits.remission.reshape(-1, k)
        return SubRayHits(t, idx, cos, rem)

    def form_echoes(
        self, hits: SubRayHits, rng: np.random.Generator | None, time_s: FloatArray | None = None
    ) -> Echoes:
        """Echo formation, systematics and noise from the sub-ray hits (``time_s``: per beam or None).

        The echoes are formed in chunks of at most ``chunk_rays`` and 2^16 sub-rays (whole beams),
        so the working arrays stay small whatever the number of beams; the noise is drawn once for
        all beams afterwards (the same draws as without chunks: the result does not depend on them).
        """
        n, k = hits.range.shape
        if k != self.footprint.sub_rays:
            raise SceneError(f"sub-ray hits have {k} sub-rays per beam, the footprint {self.footprint.sub_rays}")
        times = None if time_s is None else np.broadcast_to(np.asarray(time_s, dtype=np.float64), (n,))
        _, _, w = self.footprint.pattern()
        one, two = _Picked.empty(n), _Picked.empty(n)
        step = max(1, min(self.chunk_rays, _ECHO_CHUNK_RAYS) // k)
        for lo in range(0, n, step):
            hi = min(n, lo + step)
            part = SubRayHits(hits.range[lo:hi], hits.index[lo:hi], hits.cos_incidence[lo:hi], hits.remission[lo:hi])
            c = _clusters(part, w, self.echo_separation_m, self.range_min, self.edge_threshold)
            self._pick_echoes(c, one, two, lo)
        first = self._echo(one, rng, times)
        second = self._echo(two, rng, times)
        return dataclasses.replace(
            first,
            range2=second.range,
            valid2=second.valid,
            true_range2=second.true_range,
            index2=second.index,
            rssi2=second.rssi,
        )

    def _pick_echoes(self, c: _Clusters, one: _Picked, two: _Picked, lo: int) -> None:
        """Detect the clusters ``c`` of beams ``lo..`` and store their DIST1 / DIST2 echoes."""
        m, k = c.weight.shape
        r_echo = c.first_range if self.range_mode == "first" else c.weighted_range
        det = (
            (c.weight > 0)
            & (c.weight >= self.edge_threshold * (1 - 1e-12))
            & (c.energy >= self.min_energy)
            & (c.energy > 0)
            & (r_echo >= self.range_min)
            & (r_echo <= self.range_max)
        )
        rows = np.arange(m)
        any1: NDArray[np.bool_] = np.asarray(det.any(axis=1), dtype=bool)
        c1 = np.argmax(det, axis=1)
        rest = det.copy()
        rest[rows, c1] = False
        any2: NDArray[np.bool_] = np.asarray(rest.any(axis=1), dtype=bool)
        c2 = np.argmax(rest, axis=1)
        if self.echo_filter == "first":
            one.put(lo, c, r_echo, rows, c1, any1)
            two.put(lo, c, r_echo, rows, c2, any2)
        else:
            one.put(lo, c, r_echo, rows, k - 1 - np.argmax(det[:, ::-1], axis=1), any1)
            two.put(lo, c, r_echo, rows, c1, any2)

    def _echo(self, p: _Picked, rng: np.random.Generator | None, time_s: FloatArray | None) -> Echoes:
        """One reported echo per beam (``p``, where ``p.present``): systematics, noise, RSSI."""
        present = p.present
        e_safe = np.where(present, p.energy, 1.0)
        t_safe = np.where(present, p.true_range, 1.0)
        rng_out = self.systematics.apply(t_safe, e_safe, p.cos, time_s)
        if rng is not None:
            var = (
                self.sigma_typical**2
                + (self.sigma_max**2 - self.sigma_typical**2) * np.minimum(1.0, self.min_energy / e_safe)
                + (self.spread_noise * p.spread) ** 2
            )
            rng_out = rng_out + rng.standard_normal(rng_out.shape) * np.sqrt(var)
        if self.quantum > 0:
            rng_out = np.round(rng_out / self.quantum) * self.quantum
        rng_out = np.where(present, np.maximum(rng_out, 0.0), 0.0)
        atten = np.minimum(1.0, self.rssi_reference_m / t_safe) ** self.rssi_range_exponent
        rssi = np.where(present, self.rssi_gain * p.wrc * atten, 0.0)
        return Echoes(
            range=np.asarray(rng_out, dtype=np.float64),
            valid=present,
            true_range=p.true_range,
            index=p.index,
            cos_incidence=p.cos,
            remission=p.remission,
            rssi=rssi,
            coverage=p.weight,
            energy=p.energy,
        )


@dataclass(frozen=True)
class SubRayHits:
    """Sub-ray hits of ``N`` beams, arrays ``(N, K)``: range (inf: miss), object index (-1),
    |cos incidence| and remission (0 for a miss)."""

    range: FloatArray
    index: NDArray[np.intp]
    cos_incidence: FloatArray
    remission: FloatArray


@dataclass(frozen=True)
class _Clusters:
    """Per beam and echo (cluster ``j`` in range order), arrays ``(N, K)``; unused clusters 0."""

    weight: FloatArray  # share of the spot's profile
    energy: FloatArray  # sum of weight * remission * cos / range^2
    weighted_range: FloatArray  # energy-weighted mean range
    first_range: FloatArray  # leading edge: where the accumulated weight reaches the threshold
    spread: FloatArray  # energy-weighted std of the sub-ray ranges
    cos: FloatArray  # weight-weighted mean |cos incidence|
    remission: FloatArray  # weight-weighted mean remission
    wrc: FloatArray  # sum of weight * remission * cos (no range term)
    index: NDArray[np.intp]  # the object that returned most of the echo's energy


@dataclass(frozen=True)
class _Picked:
    """One reported echo per beam, arrays ``(N,)``; beams without it: 0 (``true_range`` inf,
    ``index`` -1). Filled chunk by chunk from :class:`_Clusters` (:meth:`put`)."""

    present: NDArray[np.bool_]
    energy: FloatArray
    weight: FloatArray
    cos: FloatArray
    true_range: FloatArray
    spread: FloatArray
    wrc: FloatArray
    remission: FloatArray
    index: NDArray[np.intp]

    @staticmethod
    def empty(n: int) -> _Picked:
        e, w, c, t, s, a, r = (np.empty(n) for _ in range(7))
        return _Picked(np.empty(n, dtype=bool), e, w, c, t, s, a, r, np.empty(n, dtype=np.intp))

    def put(
        self,
        lo: int,
        c: _Clusters,
        r_echo: FloatArray,
        rows: NDArray[np.intp],
        col: NDArray[np.intp],
        present: NDArray[np.bool_],
    ) -> None:
        """Beams ``lo..lo + len(rows)``: cluster ``col`` of each row of ``c`` where ``present``."""
        s = slice(lo, lo + rows.size)
        self.present[s] = present
        self.energy[s] = np.where(present, c.energy[rows, col], 0.0)
        self.weight[s] = np.where(present, c.weight[rows, col], 0.0)
        self.cos[s] = np.where(present, c.cos[rows, col], 0.0)
        self.true_range[s] = np.where(present, r_echo[rows, col], np.inf)
        self.spread[s] = np.where(present, c.spread[rows, col], 0.0)
        self.wrc[s] = np.where(present, c.wrc[rows, col], 0.0)
        self.remission[s] = np.where(present, c.remission[rows, col], 0.0)
        self.index[s] = np.where(present, c.index[rows, col], -1)


def _clusters(hits: SubRayHits, w: FloatArray, separation: float, range_min: float, threshold: float) -> _Clusters:
    """Group each beam's sub-rays into echoes: sorted by range, a gap > ``separation`` splits.

    ``first_range``: where the echo's accumulated profile weight (sub-rays in range order) reaches
    ``threshold`` (its first sub-ray for 0): the leading edge seen by a threshold discriminator.
    """
    n, k = hits.range.shape
    order = np.argsort(hits.range, axis=1, kind="stable")
    ts = np.take_along_axis(hits.range, order, axis=1)
    hit = np.isfinite(ts)
    ws = np.where(hit, w[order], 0.0)
    cs = np.take_along_axis(hits.cos_incidence, order, axis=1)
    rs = np.take_along_axis(hits.remission, order, axis=1)
    idx = np.take_along_axis(hits.index, order, axis=1)
    tf = np.where(hit, ts, 0.0)
    wrc = ws * rs * cs
    es = wrc / np.maximum(np.where(hit, ts, 1.0), range_min) ** 2
    new = np.zeros((n, k), dtype=bool)
    with np.errstate(invalid="ignore"):
        new[:, 1:] = (ts[:, 1:] - ts[:, :-1]) > separation  # inf - inf is nan: misses stay together
    cid = np.cumsum(new, axis=1)
    flat = (np.arange(n)[:, None] * k + cid).ravel()
    size = n * k

    def total(values: FloatArray) -> FloatArray:
        return np.asarray(np.bincount(flat, weights=values.ravel(), minlength=size), dtype=np.float64).reshape(n, k)

    weight = total(ws)
    energy = total(es)
    er = total(es * tf)
    er2 = total(es * tf * tf)
    e_safe = np.where(energy > 0, energy, 1.0)
    w_safe = np.where(weight > 0, weight, 1.0)
    mean = er / e_safe
    spread = np.sqrt(np.maximum(er2 / e_safe - mean * mean, 0.0))
    cum = np.cumsum(ws, axis=1)
    before = (cum - ws).ravel()  # accumulated weight before each sub-ray, from the row's start
    start_cum = np.zeros(size)
    starts = (new | (np.arange(k) == 0)[None, :]).ravel()
    start_cum[flat[starts]] = before[starts]
    inside = cum.ravel() - start_cum[flat]  # accumulated weight within the sub-ray's echo
    level = max(threshold, 1e-12) * (1 - 1e-12)
    crossing = hit.ravel() & (inside >= level) & (inside - ws.ravel() < level)
    first = np.full(size, np.inf)
    first[flat[crossing]] = ts.ravel()[crossing]
    index = np.where(energy.ravel() > 0, _main_object(flat, idx.ravel(), es.ravel(), size), -1)
    return _Clusters(
        weight=weight,
        energy=energy,
        weighted_range=np.where(energy > 0, mean, np.inf),
        first_range=first.reshape(n, k),
        spread=spread,
        cos=total(ws * cs) / w_safe,
        remission=total(ws * rs) / w_safe,
        wrc=total(wrc),
        index=np.asarray(index, dtype=np.intp).reshape(n, k),
    )


#: Names accepted by :func:`make_sensor` (config ``[sim] sensor``, ``lrms sim scanner --sensor``).
SENSOR_NAMES = ("ideal", "lms1xx")
#: Sub-rays per beam of the streaming device's "lms1xx" sensor (:func:`make_sensor`): fewer than
#: :class:`Footprint`'s 128 so that a real-time simulated LMS100 keeps near 25 Hz; its first-hit
#: sampling moves a footprint fit by up to ~1-2 mm (docs/sensor-model.md, "Cost").
STREAM_SUB_RAYS = 32


def sensor_name(sensor: Sensor) -> str:
    """The :data:`SENSOR_NAMES` entry of a sensor model's kind ("ideal" or "lms1xx")."""
    return "lms1xx" if isinstance(sensor, LMS1xxSensor) else "ideal"


def make_sensor(name: str, sigma_l: float | None = None, sigma_alpha: float | None = None,
                sigma_beta: float | None = None) -> Sensor:  # fmt: skip
    """A sensor model by name: "ideal" (thin beam, :class:`SensorModel`) or "lms1xx" (footprint,
    :data:`STREAM_SUB_RAYS` sub-rays per beam: the streaming device's speed over sampling accuracy).

    ``sigma_l`` / ``sigma_alpha`` / ``sigma_beta`` (m, rad; None = the model's default) set the
    noise; the LMS1xx model takes only the two angle figures (its range noise is SICK's).
    """
    if name == "ideal":
        kw = {k: v for k, v in (("sigma_l", sigma_l), ("sigma_alpha", sigma_alpha), ("sigma_beta", sigma_beta))}
        return SensorModel(**{k: float(v) for k, v in kw.items() if v is not None})
    if name == "lms1xx":
        base = LMS1xxSensor(footprint=Footprint(sub_rays=STREAM_SUB_RAYS))
        return dataclasses.replace(
            base,
            sigma_alpha=base.sigma_alpha if sigma_alpha is None else float(sigma_alpha),
            sigma_beta=base.sigma_beta if sigma_beta is None else float(sigma_beta),
        )
    raise SceneError(f"unknown sensor model {name!r} (known: {', '.join(SENSOR_NAMES)})")


def _main_object(cluster: NDArray[np.intp], obj: NDArray[np.intp], energy: FloatArray, size: int) -> NDArray[np.intp]:
    """Per cluster ``0..size-1``: the object (index >= 0) whose sub-rays carry most of the energy
    (the lowest index on a tie; -1 without a hit). ``cluster`` must be non-decreasing.

    The energy is summed per (cluster, object) over the clusters with a hit only: a dense table
    (hit clusters x objects) while it holds at most :data:`_DENSE_OBJECT_TABLE` entries per
    sub-ray, else over the pairs that occur (sorted keys), so memory stays bounded by the chunk.
    """
    out = np.full(size, -1, dtype=np.intp)
    hit = obj >= 0
    if not hit.any():
        return out
    objects = int(obj.max()) + 1
    ch, oh, eh = cluster[hit], obj[hit], energy[hit]
    change = np.ones(ch.size, dtype=bool)
    change[1:] = ch[1:] != ch[:-1]
    owners = ch[change]  # the clusters with a hit, in order
    if owners.size * objects <= _DENSE_OBJECT_TABLE * cluster.size:
        rank = np.cumsum(change) - 1
        table = np.bincount(rank * objects + oh, weights=eh, minlength=owners.size * objects)
        out[owners] = np.argmax(table.reshape(owners.size, objects), axis=1)
        return out
    pairs, inverse = np.unique(ch.astype(np.int64) * objects + oh, return_inverse=True)
    sums = np.bincount(inverse.ravel(), weights=eh, minlength=pairs.size)
    owner = pairs // objects
    best = np.lexsort((-sums, owner))  # per cluster: most energy first, ties by object (stable)
    lead = np.ones(best.size, dtype=bool)
    lead[1:] = owner[best[1:]] != owner[best[:-1]]
    out[owner[best[lead]]] = pairs[best[lead]] % objects
    return out
