"""``lrms motor --motor URL ACTION``: one servo command from the command line.

Actions: ``status``, ``enable``, ``disable``, ``home``, ``move DEG``, ``jog DEG_PER_S``, ``stop``,
``reset``. ``move``, ``jog`` and ``home`` enable the drive first if needed; ``move`` and ``home``
wait for completion. The drive keeps its state when the command ends (a jog keeps turning until
``lrms motor stop``). ``status`` on a ``canopen+`` URL joins passively (``setup=0&sync_hz=0``:
no NMT, no re-mapping, no SYNC), so it can watch a drive another process is running.
Angles are degrees at the output shaft; ``--config FILE`` reads the ``[motor]`` table of a TOML
file as the drive configuration (counts per revolution, gear ratio, limits, speeds; see
docs/servo.md).
"""

from __future__ import annotations

import argparse

HELP = "command a servo motor: status, enable, disable, home, move DEG, jog DEG_PER_S, stop, reset"

_ACTIONS = ("status", "enable", "disable", "home", "move", "jog", "stop", "reset")


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--motor", required=True, metavar="URL", help="e.g. canopen+socketcand://127.0.0.1:29536/can0?node=1"
    )
    parser.add_argument("--config", metavar="TOML", help="drive configuration file ([motor] table)")
    parser.add_argument("--velocity", type=float, metavar="DEG_PER_S", help="move velocity (default from config)")
    parser.add_argument("--acceleration", type=float, metavar="DEG_PER_S2", help="acceleration (default from config)")
    parser.add_argument("--timeout", type=float, default=None, metavar="S", help="seconds to wait for move/home")
    parser.add_argument("action", choices=_ACTIONS)
    parser.add_argument("value", nargs="?", type=float, help="degrees for move, degrees/s for jog")


def _load_config(path: str | None) -> object:
    from drivers.servo.interface import DriveConfig

    if path is None:
        return DriveConfig()
    import tomllib
    from pathlib import Path

    from drivers.servo.interface import DriveConfigError

    try:
        data = tomllib.loads(Path(path).read_text())
    except (OSError, tomllib.TOMLDecodeError) as exc:
        raise DriveConfigError(f"cannot read {path}: {exc}") from exc
    table = data.get("motor", {})
    if not isinstance(table, dict):
        raise DriveConfigError(f"{path}: [motor] is not a table")
    table = {k: v for k, v in table.items() if k != "url"}  # a rig file names the device there too
    return DriveConfig.from_dict(table)


def run(args: argparse.Namespace) -> int:
    import math

    from drivers.servo import cia402
    from drivers.servo.interface import Motor
    from drivers.url import open_device

    if args.action in ("move", "jog") and args.value is None:
        raise SystemExit(f"lrms motor: error: {args.action} needs a value")
    if args.action not in ("move", "jog") and args.value is not None:
        raise SystemExit(f"lrms motor: error: {args.action} takes no value")
    config = _load_config(args.config)
    velocity = None if args.velocity is None else math.radians(args.velocity)
    acceleration = None if args.acceleration is None else math.radians(args.acceleration)
    url = args.motor
    if args.action == "status":
        url = _passive(url)
    motor: Motor = open_device("motor", url, config=config)
    try:
        action = args.action
        if action in ("move", "jog", "home") and motor.state is not cia402.State.OPERATION_ENABLED:
            motor.enable()
        if action == "enable":
            motor.enable()
        elif action == "disable":
            motor.disable()
        elif action == "reset":
            motor.reset_fault()
        elif action == "stop":
            motor.stop()
            motor.wait_reached(args.timeout or 10.0)
        elif action == "home":
            motor.home(timeout=args.timeout or 30.0)
        elif action == "move":
            motor.move_to(math.radians(args.value), velocity, acceleration, wait=True, timeout=args.timeout)
        elif action == "jog":
            motor.jog(math.radians(args.value), acceleration)
        _print_status(motor)
    finally:
        motor.close()
    return 0


def _passive(url: str) -> str:
    """``status`` must not disturb a master that runs the drive: join a CANopen bus passively
    (no NMT, no re-mapping, no SYNC of our own) unless the URL says otherwise."""
    from drivers.url import DeviceURL

    parsed = DeviceURL.parse(url)
    if not parsed.scheme.startswith("canopen+"):
        return url
    extra = [opt for opt in ("setup=0", "sync_hz=0") if not parsed.has(opt.split("=")[0])]
    if not extra:
        return url
    return url + ("&" if "?" in url else "?") + "&".join(extra)


def _print_status(motor: object) -> None:
    import math

    from drivers.servo import cia402
    from drivers.servo.interface import Motor

    assert isinstance(motor, Motor)
    sw = motor.statusword
    print(f"state: {cia402.describe_statusword(sw)}")
    print(f"position_deg: {math.degrees(motor.position_rad()):.4f}")
    print(f"velocity_deg_s: {math.degrees(motor.velocity_rad_s()):.4f}")
    fault = motor.fault()
    if fault is None:
        print("fault: none")
    else:
        print(f"fault: 0x{fault.code:04X} {fault.reason}")
