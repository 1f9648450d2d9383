"""``lrms scan``: read scans from an LMS100 and print them, one JSON object per line.

Examples::

    lrms scan --scanner 'tcp://192.168.0.1:2112?cola=b' --count 10
    lrms scan --scanner 'tcp://127.0.0.1:2111?cola=a&timeout=2' --count 3 --poll

Each line carries the scan header (telegram and scan counters, device clock in us, scan
frequency, device status, serial number), the DIST1 geometry (start angle and step in the
device's degrees) and the values: ``ranges_m`` (metres, 0 = no echo) and ``rssi`` (or null).
If the device is not measuring (STlms state 7), the command logs in, starts the measurement and
sends Run first (``--no-start`` only reads). ``--stats`` prints the client's link statistics
(received, lost, gaps, reconnects, ...) as one JSON line on stderr at the end.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from drivers.lms100.client import ScannerClient
    from drivers.lms100.scan import Scan

HELP = "read scans from an LMS100 (tcp://HOST:PORT?cola=a|b) and print them as JSON lines"


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--scanner", required=True, metavar="URL", help="scanner URL, e.g. tcp://HOST:2112?cola=b")
    parser.add_argument("--count", type=int, default=1, metavar="N", help="number of scans to print (0: until ^C)")
    parser.add_argument("--format", choices=("jsonl",), default="jsonl", help="output format (one JSON object a line)")
    parser.add_argument("--poll", action="store_true", help="ask for each scan (sRN LMDscandata) instead of streaming")
    parser.add_argument("--no-start", action="store_true", help="do not log in and start the measurement")
    parser.add_argument("--stats", action="store_true", help="print the link statistics as JSON on stderr at the end")


def scan_record(scan: Scan) -> dict[str, Any]:
    """The JSON object printed for one scan (units in the field names)."""
    import numpy as np

    rssi = scan.rssi
    return {
        "telegram_counter": scan.telegram_counter,
        "scan_counter": scan.scan_counter,
        "time_since_startup_us": scan.time_since_startup_us,
        "time_of_transmission_us": scan.time_of_transmission_us,
        "scan_frequency_hz": scan.scan_frequency_hz,
        "measurement_frequency_hz": scan.measurement_frequency_hz,
        "start_angle_deg": scan.start_angle_deg,
        "angular_step_deg": scan.angular_step_deg,
        "device_status": list(scan.device_status),
        "serial_number": scan.serial_number,
        "device_number": scan.device_number,
        "ranges_m": np.round(scan.ranges_m, 6).tolist(),
        "rssi": None if rssi is None else np.round(rssi, 6).tolist(),
    }


def _polled(client: ScannerClient, count: int) -> Any:
    """Poll until ``count`` distinct scans (a poll inside one scan period repeats the last scan)."""
    last: int | None = None
    n = 0
    while count == 0 or n < count:
        scan = client.poll()
        if scan.scan_counter == last:
            time.sleep(0.25 / max(scan.scan_frequency_hz, 1.0))
            continue
        last = scan.scan_counter
        n += 1
        yield scan


def run(args: argparse.Namespace) -> int:
    from drivers.errors import DriverError
    from drivers.url import open_device

    if args.count < 0:
        raise DriverError(f"--count must be >= 0, got {args.count}")
    client: ScannerClient = open_device("scanner", args.scanner)
    out = sys.stdout
    try:
        if not args.no_start:
            client.ensure_measuring()
        if args.poll:
            scans = _polled(client, args.count)
        else:
            client.start_streaming()
            scans = client.scans(None if args.count == 0 else args.count)
        for scan in scans:
            out.write(json.dumps(scan_record(scan), separators=(",", ":")) + "\n")
            out.flush()
    except BrokenPipeError:  # `lrms scan ... | head -1`: the reader left, which is not an error
        os.dup2(os.open(os.devnull, os.O_WRONLY), out.fileno())
        return 0
    finally:
        client.close()
        if args.stats:
            print(json.dumps(client.stats.as_dict()), file=sys.stderr)
    return 0
