"""One simulated rig on one clock: a simulated LMS100 on a simulated tilt drive.

The drive (:class:`sim.drive.model.SimDrive`) and the scanner (:class:`SimulatedLMS100`) both run
on the host's monotonic clock (system-wide on Linux, so other processes share it). The scanner
ray-casts every beam with the drive's shaft angle *at that beam's instant*: a recorder thread
samples the drive's actual position every ``history_period_s`` (advancing its physics to that
instant first), and the scanner's ``motor_angle_at`` interpolates that history at the beam
times (device clock -> host monotonic time via the scanner's own clock), bringing the history
up to the present first. So the scan plane keeps turning while a scan is taken, as on the rig.

Both devices are served over real transports: the scanner over TCP on 127.0.0.1 (CoLa A or B),
the drive as a CANopen node on a socketcand server on 127.0.0.1 (or a python-can ``virtual``
channel in this process). :attr:`SimulatedRig.scanner_url` and :attr:`SimulatedRig.motor_url`
are what a client opens (:func:`drivers.url.open_device`).
"""

from __future__ import annotations

import contextlib
import itertools
import threading
import time
from collections.abc import Callable
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from drivers.servo import cia402
from drivers.servo.interface import DriveConfig
from lrms.kinematics import RigCalibration
from sim.drive.model import SimDrive
from sim.scanner.device import SimulatedLMS100
from sim.scanner.server import ScannerServer
from sim.scene import SENSOR_NAMES, Scene, Sensor, make_sensor, sensor_name

FloatArray = NDArray[np.float64]
_channels = itertools.count(1)
#: The heartbeat tolerance the simulated rig's motor URL asks of the CANopen driver, in heartbeat
#: periods (``heartbeat_lost``; 100 ms each): 2 s instead of the driver's 0.5 s. The simulated drive
#: and the driver share the host's CPUs with everything else; at load 9-11 on two cores an idle
#: ``lrms serve`` faulted its simulated drive (``heartbeat lost: node 1 silent for 511-1015 ms``)
#: before about half its sweeps. A real rig keeps the driver's default (its drive runs on its own
#: hardware); a test of the watchdog itself sets its own URL.
SIM_HEARTBEAT_LOST = 20
#: The control channel's commands (one per line on the stdin of ``python -m sim.rig``).
COMMANDS = ("drop_scanner", "kill_scanner", "motor_fault [KIND]", "drive_state", "scanner_stats", "describe")


class PositionHistory:
    """Timestamped shaft angles of a :class:`SimDrive` (host monotonic s, output-shaft rad)."""

    def __init__(self, drive: SimDrive, config: DriveConfig, capacity: int = 1 << 16) -> None:
        self.drive = drive
        self.config = config
        self._cap = capacity
        self._t = np.zeros(capacity)
        self._a = np.zeros(capacity)
        self._n = 0
        self._lock = threading.Lock()

    def sample(self) -> None:
        """Advance the drive's physics to now and record its actual position."""
        with self.drive.lock:
            t = self.drive.clock()
            counts = self.drive.read(cia402.POSITION_ACTUAL)
        angle = self.config.counts_to_rad(counts)
        with self._lock:
            if self._n and t <= self._t[(self._n - 1) % self._cap]:
                return
            i = self._n % self._cap
            self._t[i] = t
            self._a[i] = angle
            self._n += 1

    def arrays(self) -> tuple[FloatArray, FloatArray]:
        with self._lock:
            n = min(self._n, self._cap)
            order = np.arange(self._n - n, self._n) % self._cap
            return self._t[order].copy(), self._a[order].copy()

    def angle_at(self, t_host: ArrayLike) -> FloatArray:
        """Shaft angle at host monotonic times (linear between samples, held at the ends)."""
        self.sample()
        t, a = self.arrays()
        return np.interp(np.asarray(t_host, dtype=np.float64), t, a)


class SimulatedRig:
    """The simulated scanner and drive of one rig, served on 127.0.0.1 (see the module docstring)."""

    def __init__(
        self,
        scene: Scene | str = "seed003",
        calibration: RigCalibration | None = None,
        sensor: Sensor | None = None,
        *,
        seed: int = 0,
        cola: str = "b",
        can: str = "socketcand",
        node: int = 1,
        drive_config: DriveConfig | None = None,
        history_period_s: float = 0.002,
    ) -> None:
        if can not in ("socketcand", "virtual"):
            raise ValueError(f"can must be 'socketcand' or 'virtual', got {can!r}")
        self.calibration = calibration if calibration is not None else RigCalibration()
        self.drive_config = drive_config if drive_config is not None else DriveConfig()
        self.drive = SimDrive(node, clock=time.monotonic)
        self.history = PositionHistory(self.drive, self.drive_config)
        self.history.sample()
        self._stop = threading.Event()
        self._period = history_period_s
        self._recorder = threading.Thread(target=self._record, name="sim-rig-history", daemon=True)
        self._recorder.start()
        self._closers: list[Callable[[], None]] = [self._stop_recorder]
        try:
            self.scanner = SimulatedLMS100(
                scene, self.calibration, motor_angle_at=self._motor_angle_at, sensor=sensor, seed=seed, realtime=True
            )
            self.scanner_server = ScannerServer(self.scanner, dialect=cola).start()
            self._closers.append(self.scanner_server.stop)
            self.can_kind = can
            if can == "socketcand":
                from sim.drive.socketcand import SimulatedCanDrive

                self.can_drive: Any = SimulatedCanDrive(node=node, drive=self.drive)
                self._closers.append(self.can_drive.close)
                self.motor_url = f"{self.can_drive.url}&heartbeat_lost={SIM_HEARTBEAT_LOST:g}"
            else:
                import can as pycan

                from sim.drive.can_node import SimCanNode

                channel = f"lrms-sim-rig-{next(_channels)}-{id(self):x}"
                bus = pycan.Bus(interface="virtual", channel=channel)
                node_obj = SimCanNode(bus, self.drive, node_id=node).start()

                def stop_node() -> None:
                    node_obj.stop()
                    bus.shutdown()

                self._closers.append(stop_node)
                self.can_drive = node_obj
                self.motor_url = f"canopen+virtual://{channel}?node={node}&heartbeat_lost={SIM_HEARTBEAT_LOST:g}"
        except BaseException:
            self.close()
            raise
        self.scanner_url = self.scanner_server.url

    # -- one clock ------------------------------------------------------------------------
    def _motor_angle_at(self, device_times_s: NDArray[np.float64]) -> FloatArray:
        clock = self.scanner.clock
        if not clock.realtime:
            raise ValueError("the simulated rig needs a real-time scanner clock")
        host = clock.monotonic_at(0) + np.asarray(device_times_s, dtype=np.float64) / clock.time_scale
        return self.history.angle_at(host)

    def _record(self) -> None:
        while not self._stop.wait(self._period):
            self.history.sample()

    def _stop_recorder(self) -> None:
        self._stop.set()
        self._recorder.join(2.0)

    # -- faults ---------------------------------------------------------------------------
    def inject_motor_fault(self, kind: str = "following_error") -> None:
        """``following_error`` (the axis stalls), ``over_current`` or ``heartbeat_loss``."""
        self.drive.inject_fault(kind)

    def drop_scanner_connections(self) -> int:
        """Cut every scanner client's TCP connection (as a cable pull would)."""
        return self.scanner_server.drop_clients()

    def kill_scanner(self) -> None:
        """The scanner goes dead (power loss): its connections are cut and it stops listening."""
        self.scanner_server.stop()

    def drive_state(self) -> dict[str, Any]:
        """The drive's CiA 402 state and actual velocity (counts/s), read after advancing its physics."""
        with self.drive.lock:
            velocity = int(self.drive.read(cia402.VELOCITY_ACTUAL))
            return {"state": self.drive.state.name, "velocity_actual": velocity}

    def scanner_stats(self) -> dict[str, int]:
        """Scans the simulated scanner streamed (``sent``) and passed over because it fell behind
        real time (``skipped``: gaps that a starved host, not the client, made)."""
        server = self.scanner_server
        return {"sent": server.scans_sent, "skipped": server.scans_skipped}

    def command(self, line: str) -> dict[str, Any]:
        """One line of the control channel of ``python -m sim.rig`` (see :func:`main`)."""
        words = line.split()
        if not words:
            raise ValueError("empty command")
        cmd, args = words[0], words[1:]
        if cmd == "drop_scanner":
            return {"ok": True, "dropped": self.drop_scanner_connections()}
        if cmd == "kill_scanner":
            self.kill_scanner()
            return {"ok": True}
        if cmd == "motor_fault":
            self.inject_motor_fault(args[0] if args else "following_error")
            return {"ok": True}
        if cmd == "drive_state":
            return {"ok": True, **self.drive_state()}
        if cmd == "scanner_stats":
            return {"ok": True, **self.scanner_stats()}
        if cmd == "describe":
            return {"ok": True, **self.describe()}
        raise ValueError(f"unknown command {cmd!r} (known: {', '.join(COMMANDS)})")

    def describe(self) -> dict[str, Any]:
        return {
            "scene": self.scanner.scene.name,
            "sensor": sensor_name(self.scanner.sensor),
            "scanner_url": self.scanner_url,
            "motor_url": self.motor_url,
            "can": self.can_kind,
        }

    def close(self) -> None:
        while self._closers:
            closer = self._closers.pop()
            with contextlib.suppress(Exception):  # best effort: close everything else too
                closer()

    def __enter__(self) -> SimulatedRig:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def main(argv: list[str] | None = None) -> int:
    """``python -m sim.rig``: serve one simulated rig until stdin closes (or Ctrl-C).

    Prints one JSON line with ``scanner_url`` and ``motor_url`` once both are listening, so a
    service in another process can be pointed at them (hardware-in-the-loop tests). Each line
    then read from stdin is a control command (fault injection; :data:`COMMANDS`), answered by
    one JSON line on stdout: ``drop_scanner`` (cut the scanner's connections), ``kill_scanner``
    (the scanner goes dead), ``motor_fault KIND`` (``following_error``, ``over_current``,
    ``heartbeat_loss``), ``drive_state``, ``scanner_stats`` (scans ``sent`` and ``skipped``),
    ``describe``; an error is ``{"ok": false, "error"}``.
    """
    import argparse
    import json
    import sys

    parser = argparse.ArgumentParser(prog="python -m sim.rig", description=main.__doc__)
    parser.add_argument("--scene", default="seed003")
    parser.add_argument("--sensor", choices=SENSOR_NAMES, default="ideal", help="sensor model (default ideal)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--cola", choices=("a", "b"), default="b")
    parser.add_argument("--can", choices=("socketcand",), default="socketcand")
    parser.add_argument("--node", type=int, default=1)
    parser.add_argument("--kinematics", default="{}", help="JSON table as in the rig TOML [kinematics]")
    parser.add_argument(
        "--rig-errors",
        default="{}",
        help="JSON: the rig's true departures from --kinematics (as [sim] rig_errors: range_offset_m, "
        "range_scale_ppm, p_m, q_m, tilt_x_deg, tilt_y_deg, alpha_zero_deg, beta_zero_deg, motor_scale_ppm, "
        "backlash_deg, time_offset_s)",
    )
    parser.add_argument("--noise", default="{}", help="JSON: sigma_l (m), sigma_alpha, sigma_beta (rad)")
    args = parser.parse_args(argv)
    calibration = RigCalibration.from_dict({**json.loads(args.kinematics), **json.loads(args.rig_errors)})
    noise = json.loads(args.noise)
    unknown = set(noise) - {"sigma_l", "sigma_alpha", "sigma_beta"}
    if unknown:
        parser.error(f"--noise: unknown keys {sorted(unknown)} (sigma_l in m, sigma_alpha and sigma_beta in rad)")
    sensor = make_sensor(args.sensor, **{k: float(v) for k, v in noise.items()})
    with SimulatedRig(
        args.scene, calibration, sensor, seed=args.seed, cola=args.cola, can=args.can, node=args.node
    ) as rig:
        print(json.dumps(rig.describe()), flush=True)
        with contextlib.suppress(KeyboardInterrupt):
            for line in sys.stdin:  # until the parent closes our stdin
                if not line.strip():
                    continue
                try:
                    reply = rig.command(line)
                except (ValueError, LookupError) as exc:
                    reply = {"ok": False, "error": str(exc)}
                print(json.dumps(reply), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
