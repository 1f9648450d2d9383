"""``lrms sim scanner``: serve a simulated SICK LMS100 over TCP (CoLa A or B) until Ctrl-C."""

from __future__ import annotations

import argparse
import logging
import sys

HELP = "serve a simulated SICK LMS100 (CoLa A/B over TCP) with ray-cast scans of a scene"


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--host", default="127.0.0.1", help="address to listen on (default 127.0.0.1)")
    parser.add_argument(
        "--port", type=int, default=None, help="TCP port (default 2111 for CoLa A, 2112 for CoLa B; 0 = any free port)"
    )
    parser.add_argument("--cola", choices=("a", "b"), default="b", help="CoLa dialect (default b)")
    parser.add_argument("--scene", default="seed003", help="scene name (see --list-scenes; default seed003)")
    parser.add_argument("--list-scenes", action="store_true", help="print the scene names and exit")
    parser.add_argument(
        "--sensor",
        choices=("ideal", "lms1xx"),
        default="ideal",
        help="sensor model: ideal (thin beam, seed 003's noise; default) or lms1xx (beam footprint, echoes, RSSI)",
    )
    mode = parser.add_mutually_exclusive_group()
    mode.add_argument("--realtime", dest="realtime", action="store_true", default=True, help="stream at 25/50 Hz")
    mode.add_argument(
        "--fast", dest="realtime", action="store_false", help="stream as fast as clients read (virtual device clock)"
    )
    parser.add_argument("--time-scale", type=float, default=1.0, help="real-time mode: device clock speed-up")
    parser.add_argument("--seed", type=int, default=0, help="noise seed (default 0)")
    parser.add_argument(
        "--rig-errors",
        default="{}",
        metavar="JSON",
        help="the simulated rig's true errors, as [sim] rig_errors (e.g. '{\"range_offset_m\": 0.02}')",
    )


def run(args: argparse.Namespace) -> int:
    from sim.scanner import ScannerServer, SimulatedLMS100
    from sim.scene import describe_scene, list_scenes, make_sensor

    if args.list_scenes:
        for name in list_scenes():
            print(f"{name:16s} {describe_scene(name)}")
        return 0
    # rejected requests are logged by the device (WARNING): show them with time and source
    logging.basicConfig(level=logging.WARNING, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    port = args.port if args.port is not None else (2111 if args.cola == "a" else 2112)
    import json

    from lrms.kinematics import RigCalibration

    try:
        calibration = RigCalibration.from_dict(json.loads(args.rig_errors))
    except json.JSONDecodeError as exc:
        raise SystemExit(f"error: --rig-errors is not JSON: {exc}") from None
    device = SimulatedLMS100(
        args.scene,
        calibration,
        sensor=make_sensor(args.sensor),
        seed=args.seed,
        realtime=args.realtime,
        time_scale=args.time_scale,
    )
    server = ScannerServer(device, host=args.host, port=port, dialect=args.cola)
    mode = "real time" if args.realtime else "fast (virtual clock)"
    try:
        server.start()
        host, bound = server.address
        where = f"tcp://{host}:{bound}?cola={args.cola}"
        print(f"simulated LMS100 on {where} scene={args.scene} sensor={args.sensor} {mode}", flush=True)
        server.serve_forever()
    except KeyboardInterrupt:
        print("stopped", file=sys.stderr)
    finally:
        server.stop()
    return 0
