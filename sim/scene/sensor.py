"""The LMS100 sensor model and beam simulation on a rig (seed 003's noise figures).

Seed 003 (Sect. 2.2) gives the per-sample variances the rig's error model uses:
``sigma_l^2 = 136.11 mm^2`` (sigma_l = 11.67 mm), ``sigma_alpha = 1.74e-3 deg`` and
``sigma_beta = 3.6e-5 deg``. The seed's text prints the two angle figures as "1.74 x 10^-30" and
"3.6 x 10^-50": we read the trailing "0" as a degree sign (our reading; the figures are then tiny
compared with the range noise, as the seed's Fig. 4 and text say: "range measurement
uncertainties contribute the most"). Both are parameters.

Simulation of one beam: the beam leaves along the *true* angles ``alpha + d_alpha``,
``beta + d_beta`` (Gaussian, the angle noise), is ray-cast against the scene, and the device
reports the nominal angles with the true range plus Gaussian range noise. Beams whose true
range lies outside ``[range_min, range_max]``, that miss everything, or whose echo
(``remission * |cos incidence|``) is below ``min_echo`` report 0, as the LMS1xx does.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Protocol, TypeVar

import numpy as np
from numpy.typing import ArrayLike, NDArray

from lrms.kinematics import RigCalibration
from sim.scene.scene import Scene
from sim.scene.shapes import FloatArray, SceneError

#: Seed 003: variance of one range sample, 136.11 mm^2.
SIGMA_L_SEED003 = float(np.sqrt(136.11e-6))
#: Seed 003: scan-angle standard deviation (1.74e-3 deg, see module notes), in rad.
SIGMA_ALPHA_SEED003 = float(np.deg2rad(1.74e-3))
#: Seed 003: motor-angle standard deviation (3.6e-5 deg, see module notes), in rad.
SIGMA_BETA_SEED003 = float(np.deg2rad(3.6e-5))


@dataclass(frozen=True)
class Echoes:
    """What a sensor model makes of ``N`` beams (flat arrays of length ``N``).

    ``range``: reported range (m, 0 = no echo); ``valid``: an echo was reported; ``true_range``:
    the noise- and systematics-free range of that echo (inf: none); ``index``: the scene object
    that gave it (-1: none); ``cos_incidence``, ``remission``: of the surface (spot means for a
    footprint model); ``rssi``: digits (0: none). A footprint model also fills ``coverage`` (the
    share of the spot's energy profile on the echo's surface, 0..1), ``energy`` (returned energy
    relative to a white target filling the spot head-on at 1 m) and the second echo (``range2``,
    ``valid2``, ``true_range2``, ``index2``, ``rssi2``: the DIST2 / RSSI2 channel); a thin-beam
    model leaves them None.
    """

    range: FloatArray
    valid: NDArray[np.bool_]
    true_range: FloatArray
    index: NDArray[np.intp]
    cos_incidence: FloatArray
    remission: FloatArray
    rssi: FloatArray
    coverage: FloatArray | None = None
    energy: FloatArray | None = None
    range2: FloatArray | None = None
    valid2: NDArray[np.bool_] | None = None
    true_range2: FloatArray | None = None
    index2: NDArray[np.intp] | None = None
    rssi2: FloatArray | None = None


def gaussian_angle_noise(
    sigma_alpha: float, sigma_beta: float, shape: tuple[int, ...], rng: np.random.Generator | None
) -> tuple[FloatArray, FloatArray]:
    """Independent normal draws of (d_alpha, d_beta) for ``shape`` beams (zeros without ``rng``):
    the angle noise of every sensor model here (the same draws in the same order)."""
    if rng is None:
        return np.zeros(shape), np.zeros(shape)
    return rng.normal(0.0, sigma_alpha, shape), rng.normal(0.0, sigma_beta, shape)


class Sensor(Protocol):
    """A sensor model: angle noise of the fired beams, and the echoes of rays in a scene.

    ``time_s``: per ray, device time since power-on (s) for warm-up drift; None = warmed up.
    """

    def angle_noise(self, shape: tuple[int, ...], rng: np.random.Generator | None) -> tuple[FloatArray, FloatArray]: ...

    def echoes(
        self,
        scene: Scene,
        origins: FloatArray,
        dirs: FloatArray,
        rng: np.random.Generator | None,
        time_s: FloatArray | None = None,
    ) -> Echoes: ...


@dataclass(frozen=True)
class SensorModel:
    """Noise, range limits and echo model of one range sample.

    ``quantum``: if > 0, reported ranges are rounded to it (the device sends whole mm; the
    simulated device always rounds to its own unit, this is for offline clouds).
    ``rssi_gain``: RSSI digits for a white (remission 1) target hit head-on.
    """

    sigma_l: float = SIGMA_L_SEED003
    sigma_alpha: float = SIGMA_ALPHA_SEED003
    sigma_beta: float = SIGMA_BETA_SEED003
    range_min: float = 0.5
    range_max: float = 20.0
    min_echo: float = 0.01
    quantum: float = 0.0
    rssi_gain: float = 200.0

    def __post_init__(self) -> None:
        for name in ("sigma_l", "sigma_alpha", "sigma_beta", "min_echo", "quantum", "rssi_gain"):
            v = getattr(self, name)
            if not np.isfinite(v) or v < 0:
                raise SceneError(f"sensor {name} must be finite and >= 0, got {v!r}")
        if not (0 <= self.range_min < self.range_max) or not np.isfinite(self.range_max):
            raise SceneError(f"sensor range limits must satisfy 0 <= min < max, got {self.range_min}, {self.range_max}")

    @classmethod
    def noiseless(cls, **kw: float) -> SensorModel:
        """A model without any noise (same limits)."""
        return cls(sigma_l=0.0, sigma_alpha=0.0, sigma_beta=0.0, **kw)

    def angle_noise(self, shape: tuple[int, ...], rng: np.random.Generator | None) -> tuple[FloatArray, FloatArray]:
        """Draws of (d_alpha, d_beta) for ``shape`` samples (zeros without ``rng``)."""
        return gaussian_angle_noise(self.sigma_alpha, self.sigma_beta, shape, rng)

    def measure(
        self,
        true_range: ArrayLike,
        echo: ArrayLike,
        rng: np.random.Generator | None,
    ) -> tuple[FloatArray, NDArray[np.bool_]]:
        """Reported ranges (m; 0 = no echo) and the validity mask from true ranges and echo strength."""
        t = np.asarray(true_range, dtype=np.float64)
        e = np.asarray(echo, dtype=np.float64)
        valid = np.isfinite(t) & (t >= self.range_min) & (t <= self.range_max) & (e >= self.min_echo) & (e > 0)
        out = np.where(valid, t, 0.0)
        if rng is not None and self.sigma_l > 0:
            out = out + np.where(valid, rng.normal(0.0, self.sigma_l, t.shape), 0.0)
        if self.quantum > 0:
            out = np.round(out / self.quantum) * self.quantum
        out = np.where(valid, np.maximum(out, 0.0), 0.0)
        return out, valid

    def rssi(self, echo: ArrayLike, valid: ArrayLike) -> FloatArray:
        """RSSI digits (0 for no echo): ``rssi_gain * remission * |cos incidence|``."""
        e = np.asarray(echo, dtype=np.float64)
        return np.where(np.asarray(valid, dtype=bool), self.rssi_gain * e, 0.0)

    def echoes(
        self,
        scene: Scene,
        origins: FloatArray,
        dirs: FloatArray,
        rng: np.random.Generator | None,
        time_s: FloatArray | None = None,
    ) -> Echoes:
        """A thin beam: one ray per beam, its first hit, Gaussian range noise (no drift: ``time_s`` unused)."""
        hits = scene.raycast(origins, dirs)
        echo = hits.remission * hits.cos_incidence
        ranges, valid = self.measure(hits.range, echo, rng)
        return Echoes(
            range=ranges,
            valid=valid,
            true_range=hits.range,
            index=hits.index,
            cos_incidence=hits.cos_incidence,
            remission=hits.remission,
            rssi=self.rssi(echo, valid),
        )


@dataclass(frozen=True)
class BeamSamples:
    """Simulated beams, all arrays of one shape ``S`` (e.g. (scans, beams)).

    ``ranges``: what the device reports (m, 0 = no echo); ``valid``: echo present;
    ``true_range``: noise-free range along the beam actually fired (inf: miss); ``index``: object
    hit (-1: none); ``cos_incidence``, ``remission``, ``rssi``; ``device_angle`` and
    ``motor_angle``: the nominal (reported) angles in rad. A footprint sensor
    (:class:`sim.scene.lms1xx.LMS1xxSensor`) also gives ``coverage``, ``energy`` and the second
    echo ``ranges2``, ``valid2``, ``true_range2``, ``index2``, ``rssi2`` (see :class:`Echoes`);
    the thin-beam :class:`SensorModel` leaves them None.
    """

    ranges: FloatArray
    valid: NDArray[np.bool_]
    true_range: FloatArray
    index: NDArray[np.intp]
    cos_incidence: FloatArray
    remission: FloatArray
    rssi: FloatArray
    device_angle: FloatArray
    motor_angle: FloatArray
    coverage: FloatArray | None = None
    energy: FloatArray | None = None
    ranges2: FloatArray | None = None
    valid2: NDArray[np.bool_] | None = None
    true_range2: FloatArray | None = None
    index2: NDArray[np.intp] | None = None
    rssi2: FloatArray | None = None

    def points(self, calibration: RigCalibration) -> FloatArray:
        """World points ``(K, 3)`` of the valid samples, mapped with the nominal angles (Eq. 1)."""
        v = self.valid
        return calibration.map_samples(self.ranges[v], self.device_angle[v], self.motor_angle[v])


_G = TypeVar("_G", bound=np.generic)


def _shaped(a: NDArray[_G] | None, shape: tuple[int, ...]) -> NDArray[_G] | None:
    return None if a is None else a.reshape(shape)


def cast_beams(
    scene: Scene,
    calibration: RigCalibration,
    sensor: Sensor,
    device_angles_rad: ArrayLike,
    motor_angles_rad: ArrayLike,
    rng: np.random.Generator | None = None,
    *,
    time_s: ArrayLike | None = None,
    motor_speed_rad_s: ArrayLike | None = None,
) -> BeamSamples:
    """Simulate samples for device beam angles and motor angles (broadcast against each other).

    Typical shapes: ``device_angles (M,)`` with ``motor_angles (S, 1)`` (one plane per scan) or
    ``(S, M)`` (the plane turns during the scan). Without ``rng`` nothing is random.
    ``time_s``: device time since power-on (s) of each beam (broadcast too), for a sensor with
    warm-up drift; None = warmed up. The rig's true geometry is ``calibration.rig``
    (:class:`lrms.kinematics.RigModel`: range offset and scale, tilts, zeros, ...);
    ``motor_speed_rad_s`` (broadcast like the angles) feeds its backlash and time-offset terms.
    """
    dev, mot = np.broadcast_arrays(
        np.asarray(device_angles_rad, dtype=np.float64), np.asarray(motor_angles_rad, dtype=np.float64)
    )
    if not (np.all(np.isfinite(dev)) and np.all(np.isfinite(mot))):
        raise SceneError("device and motor angles must be finite")
    shape = dev.shape
    d_alpha, d_beta = sensor.angle_noise(shape, rng)
    alpha = calibration.alpha(dev) + d_alpha
    beta = calibration.beta(mot) + d_beta
    speed = None if motor_speed_rad_s is None else np.broadcast_to(motor_speed_rad_s, shape).ravel()
    origins, dirs = calibration.rays(alpha.ravel(), beta.ravel(), speed)  # the rig's true geometry (RigModel)
    times = None
    if time_s is not None:
        times = np.broadcast_to(np.asarray(time_s, dtype=np.float64), shape).ravel()
        if not np.all(np.isfinite(times)):
            raise SceneError("beam times must be finite")
    e = sensor.echoes(scene, origins, dirs, rng, times)
    # the scanner reports the distance it measured through its range offset and scale (RigModel.k0, k1)
    rig = calibration.rig
    if rig.k0 != 0.0 or rig.k1 != 0.0:
        range2 = e.range2
        if range2 is not None and e.valid2 is not None:
            range2 = np.where(e.valid2, rig.reported_range(range2), 0.0)
        e = dataclasses.replace(e, range=np.where(e.valid, rig.reported_range(e.range), 0.0), range2=range2)

    return BeamSamples(
        ranges=e.range.reshape(shape),
        valid=e.valid.reshape(shape),
        true_range=e.true_range.reshape(shape),
        index=e.index.reshape(shape),
        cos_incidence=e.cos_incidence.reshape(shape),
        remission=e.remission.reshape(shape),
        rssi=e.rssi.reshape(shape),
        device_angle=np.array(dev, dtype=np.float64),
        motor_angle=np.array(mot, dtype=np.float64),
        coverage=_shaped(e.coverage, shape),
        energy=_shaped(e.energy, shape),
        ranges2=_shaped(e.range2, shape),
        valid2=_shaped(e.valid2, shape),
        true_range2=_shaped(e.true_range2, shape),
        index2=_shaped(e.index2, shape),
        rssi2=_shaped(e.rssi2, shape),
    )


def simulate_sweep(
    scene: Scene,
    calibration: RigCalibration,
    sensor: Sensor,
    device_angles_rad: ArrayLike,
    motor_angles_rad: ArrayLike,
    rng: np.random.Generator | None = None,
) -> FloatArray:
    """Reported ranges (m, 0 = no echo) for a sweep; shapes as :func:`cast_beams`.

    ``motor_angles_rad`` of shape ``(S,)`` is taken as one plane per scan (result ``(S, M)``).
    """
    mot = np.asarray(motor_angles_rad, dtype=np.float64)
    dev = np.asarray(device_angles_rad, dtype=np.float64)
    if mot.ndim == 1 and dev.ndim == 1:
        mot = mot[:, None]
    return cast_beams(scene, calibration, sensor, dev, mot, rng).ranges


def lms1xx_device_angles(resolution_deg: float = 0.25) -> FloatArray:
    """The LMS1xx beam angles in rad (-45 deg .. 225 deg): 1081 at 0.25 deg, 541 at 0.5 deg."""
    if resolution_deg not in (0.25, 0.5):
        raise SceneError(f"an LMS1xx scans at 0.25 or 0.5 deg, not {resolution_deg}")
    count = round(270 / resolution_deg) + 1
    angles: FloatArray = np.deg2rad(-45.0 + resolution_deg * np.arange(count))
    return angles


def sweep_cloud(
    scene: Scene,
    calibration: RigCalibration,
    sensor: Sensor,
    motor_angles_rad: ArrayLike,
    rng: np.random.Generator | None = None,
    resolution_deg: float = 0.25,
) -> tuple[FloatArray, BeamSamples]:
    """A whole LRMS sweep as a world-frame cloud: one LMS1xx scan per motor angle.

    Returns the valid points ``(K, 3)`` mapped with Eq. 1 from the reported ranges and nominal
    angles, and the underlying :class:`BeamSamples` of shape ``(S, beams)``.
    """
    dev = lms1xx_device_angles(resolution_deg)
    mot = np.asarray(motor_angles_rad, dtype=np.float64).reshape(-1, 1)
    samples = cast_beams(scene, calibration, sensor, dev, mot, rng)
    return samples.points(calibration), samples


def beam_times(count: int, scan_frequency_hz: float = 25.0, resolution_deg: float = 0.25) -> FloatArray:
    """Firing time (s) of beam ``j`` after the scan's first beam: one mirror turn per scan period.

    ``j * period * resolution / 360 deg``: 27.8 us per beam at 25 Hz / 0.25 deg, as the simulated
    device (:mod:`sim.scanner`) and the real LMS1xx time their beams.
    """
    if scan_frequency_hz <= 0 or resolution_deg <= 0:
        raise SceneError("scan frequency and resolution must be positive")
    times: FloatArray = np.arange(count, dtype=np.float64) * float(resolution_deg / 360.0 / scan_frequency_hz)
    return times


def continuous_sweep_cloud(
    scene: Scene,
    calibration: RigCalibration,
    sensor: Sensor,
    motor_start_rad: float,
    motor_stop_rad: float,
    speed_rad_s: float,
    rng: np.random.Generator | None = None,
    scan_frequency_hz: float = 25.0,
    resolution_deg: float = 0.25,
) -> tuple[FloatArray, BeamSamples]:
    """A sweep with the motor turning at constant speed *during* the scans (as the real rig does).

    Scan ``k`` starts at ``k / scan_frequency``; each beam gets the motor angle at its own firing
    time (:func:`beam_times`). Scans are taken while the motor is within
    ``[motor_start, motor_stop]`` (either direction). Returns the valid world points and the
    samples ``(scans, beams)``, whose ``motor_angle`` holds each beam's true motor angle.
    """
    if speed_rad_s <= 0 or not np.isfinite(speed_rad_s):
        raise SceneError(f"sweep speed must be a positive number of rad/s, got {speed_rad_s!r}")
    span = abs(motor_stop_rad - motor_start_rad)
    direction = 1.0 if motor_stop_rad >= motor_start_rad else -1.0
    period = 1.0 / scan_frequency_hz
    dev = lms1xx_device_angles(resolution_deg)
    scans = int(np.floor(span / speed_rad_s / period)) + 1
    t = np.arange(scans)[:, None] * period + beam_times(len(dev), scan_frequency_hz, resolution_deg)[None, :]
    motor = motor_start_rad + direction * np.minimum(speed_rad_s * t, span)
    omega = np.where(speed_rad_s * t < span, direction * speed_rad_s, 0.0)
    samples = cast_beams(scene, calibration, sensor, dev, motor, rng, motor_speed_rad_s=omega)
    return samples.points(calibration), samples
