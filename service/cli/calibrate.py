"""``lrms calibrate CLOUD [CLOUD...] --artefact ARTEFACT.json``: calibrate the rig (issue 12).

Each CLOUD is an .xyz / .txt / .csv / .ply file from the rig at the origin, mapped with the
nominal Eq. 1 (inner parameter ``--p``) and a sweep within beta = +-90 deg, as ``lrms fit`` reads
it; its raw readings are recovered by inverting Eq. 1. ARTEFACT.json describes what the sweeps
saw: ``{"planes": true, "spheres": [{"diameter_m": 0.2}, ...], "distances_m": [{"a": 0, "b": 1,
"distance_m": 1.0}]}``. Prints the parameters with their standard deviations and the
identifiability report (or the whole result as JSON with ``--json``); ``--out`` writes the
calibration file that ``lrms fit --calibration`` applies. See docs/calibration.md.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

HELP = "calibrate the rig from sweeps of a room and reference spheres (writes a calibration file)"


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("clouds", nargs="+", metavar="CLOUD", help="calibration sweep cloud(s): .xyz/.txt/.csv/.ply")
    parser.add_argument("--artefact", required=True, metavar="ARTEFACT.json", help="planes, spheres, distances")
    parser.add_argument("--out", metavar="CAL.json", default=None, help="write the calibration here")
    parser.add_argument("--json", action="store_true", help="print the whole result as JSON")
    parser.add_argument("--p", type=float, default=0.1, help="nominal inner parameter p of the clouds' mapping, m")
    parser.add_argument("--sigma-l-mm", type=float, default=None, help="range noise (default 11.67 mm, seed 003)")


def run(args: argparse.Namespace) -> int:
    import numpy as np

    from lrms.calibration import Artefact, ArtefactError, CalibrationError, Observations, calibrate
    from lrms.covariance import NoiseModel
    from lrms.kinematics import RigModel
    from service.pointio import read_points

    try:
        data = json.loads(Path(args.artefact).read_text(encoding="utf-8"))
    except OSError as exc:
        raise ArtefactError(f"cannot read the artefact file {args.artefact}: {exc.strerror or exc}") from None
    except json.JSONDecodeError as exc:
        raise ArtefactError(f"{args.artefact}: not JSON: {exc}") from None
    artefact = Artefact.from_dict(data)
    if not (np.isfinite(args.p) and args.p >= 0):
        raise CalibrationError(f"--p must be a length >= 0, got {args.p}")
    sweeps = []
    for name in args.clouds:
        if name.lower().endswith(".mcap"):
            raise CalibrationError(f"{name}: MCAP raw logs are not read by lrms calibrate yet; export the cloud (.ply)")
        sweeps.append(Observations.from_points(read_points(name), args.p, source=name))
    noise = NoiseModel() if args.sigma_l_mm is None else NoiseModel(sigma_l=args.sigma_l_mm / 1e3)
    result = calibrate(sweeps, artefact, nominal=RigModel(p=args.p), noise=noise)
    if args.out:
        Path(args.out).write_text(result.to_json() + "\n", encoding="utf-8")
    if args.json:
        sys.stdout.write(result.to_json() + "\n")
    else:
        _print_text(result.to_dict(), args.out)
    return 0


def _print_text(d: dict[str, Any], out: str | None) -> None:
    print(f"{'parameter':12s} {'value':>12s} {'std':>10s}  unit")
    for row in d["table"]:
        std = "held" if row["held"] else f"{row['std']:10.4g}"
        print(f"{row['name']:12s} {row['value']:12.5g} {std:>10s}  {row['unit']}")
    res = d["residuals"]
    print(
        f"{int(res['planes'])} planes, {int(res['spheres'])} spheres, {int(res['observations'])} beams, "
        f"rms range residual {1e3 * res['rms_m']:.2f} mm, variance factor {res['variance_factor']:.3f}"
    )
    ident = d["identifiability"]
    print(f"identifiability: {ident['rank']} parameters estimated, condition {ident['condition']:.3g}")
    for name, why in ident["held"].items():
        print(f"  held {name}: {why}")
    for name, why in ident["weak"].items():
        print(f"  weak {name}: {why}")
    if out:
        print(f"calibration written to {out}")
