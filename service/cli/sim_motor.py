"""``lrms sim motor --motor URL``: run a simulated servo drive until interrupted.

* ``canopen+socketcand://127.0.0.1:PORT/CHANNEL?node=N``: a socketcand-protocol server on
  127.0.0.1:PORT (0 = any free port) hosting a simulated CAN bus with the simulated CiA 402 drive
  on it as node N. Other processes open the same URL with ``lrms motor`` or the driver.
* ``modbus-rtu://...``: the simulated drive behind a Modbus RTU server
  (:func:`sim.drive.modbus_server.serve_from_url`).

The first line printed is ``serving <URL>`` with the real port, once the bus is up. For the
CANopen drive, lines on standard input steer it: ``inject following_error|over_current|
heartbeat_loss``, ``clear`` (remove injected conditions) and ``status``; each is answered with
one line (``ok ...`` or ``error ...``).
"""

from __future__ import annotations

import argparse
import importlib
import signal
import sys
import threading

HELP = "run a simulated servo drive (CANopen on a socketcand bus on 127.0.0.1, or Modbus RTU)"


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--motor",
        required=True,
        metavar="URL",
        help="canopen+socketcand://127.0.0.1:PORT/can0?node=N (PORT 0 = any free port) or modbus-rtu://...",
    )


def run(args: argparse.Namespace) -> int:
    from drivers.errors import DeviceURLError
    from drivers.url import DeviceURL

    url = DeviceURL.parse(args.motor)
    if url.scheme == "modbus-rtu":
        module = importlib.import_module("sim.drive.modbus_server")
        result: int | None = module.serve_from_url(args.motor)
        return int(result or 0)
    if url.scheme != "canopen+socketcand":
        raise DeviceURLError(
            f"lrms sim motor serves canopen+socketcand://127.0.0.1:PORT/can0?node=N or modbus-rtu://...,"
            f" not {url.scheme}:// (sim:// runs inside the process that opens it)"
        )
    from drivers.servo.cia402_can import read_url_options
    from sim.drive.socketcand import SimulatedCanDrive

    host = url.host or "127.0.0.1"
    if host not in ("127.0.0.1", "localhost"):
        raise DeviceURLError(f"the simulated CAN bus binds 127.0.0.1 only, not {host!r}")
    options = read_url_options(url)  # the driver's options are accepted (and ignored) here
    url.check_all_used()
    channel = url.path.lstrip("/") or "can0"
    stop = threading.Event()

    def on_signal(signum: int, frame: object) -> None:
        stop.set()

    previous = signal.signal(signal.SIGTERM, on_signal)
    try:
        with SimulatedCanDrive(url.port or 0, options.node, channel) as sim:
            print(f"serving {sim.url}", flush=True)
            threading.Thread(target=_stdin_commands, args=(sim.drive,), daemon=True).start()
            try:
                while not stop.wait(0.5):
                    pass
            except KeyboardInterrupt:
                pass
            print("stopped", file=sys.stderr, flush=True)
    finally:
        signal.signal(signal.SIGTERM, previous)
    return 0


def _stdin_commands(drive: object) -> None:
    """Fault injection from standard input (one command per line, one answer line each)."""
    from drivers.servo import cia402
    from sim.drive.model import SimDrive

    assert isinstance(drive, SimDrive)
    for line in sys.stdin:
        words = line.split()
        if not words:
            continue
        try:
            if words[0] == "inject" and len(words) == 2:
                drive.inject_fault(words[1])
                answer = f"ok injected {words[1]}"
            elif words == ["clear"]:
                drive.clear_injected()
                answer = "ok cleared"
            elif words == ["status"]:
                sw = drive.read(cia402.STATUSWORD)
                answer = (
                    f"ok {cia402.describe_statusword(sw)} position={drive.read(cia402.POSITION_ACTUAL)}"
                    f" error=0x{drive.read(cia402.ERROR_CODE):04X} silent={drive.silent} stalled={drive.stalled}"
                )
            else:
                answer = "error commands: inject KIND | clear | status"
        except ValueError as exc:
            answer = f"error {exc}"
        print(answer, flush=True)
