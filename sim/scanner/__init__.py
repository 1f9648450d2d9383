"""The simulated SICK LMS100: device state machine, ray-cast scans and a TCP server (CoLa A / B)."""

from sim.scanner.device import ALLOWED_SCAN_CONFIGS, DeviceClock, Session, SimulatedLMS100, SimulatorError
from sim.scanner.server import ScannerServer

__all__ = [
    "ALLOWED_SCAN_CONFIGS",
    "DeviceClock",
    "ScannerServer",
    "Session",
    "SimulatedLMS100",
    "SimulatorError",
]
