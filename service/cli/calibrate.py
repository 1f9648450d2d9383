"""``lrms calibrate CLOUD [CLOUD...] --artefact ARTEFACT.json``: calibrate the rig (issue 12).

Each CLOUD is an .xyz / .txt / .csv / .ply file from the rig at the origin, mapped with the
nominal Eq. 1 (inner parameter ``--p``) and a sweep within beta = +-90 deg, as ``lrms fit`` reads
it (its raw readings are recovered by inverting Eq. 1), or a measurement's raw MCAP log (.mcap):
its raw readings with the motor speed of every beam (what backlash and the time offset need),
the log's rig model as the nominal one (:func:`service.replay.log_readings`). ARTEFACT.json describes what the sweeps
saw: ``{"planes": true, "spheres": [{"diameter_m": 0.2}, ...], "distances_m": [{"a": 0, "b": 1,
"distance_m": 1.0}]}``. Prints the parameters with their standard deviations and the
identifiability report (or the whole result as JSON with ``--json``); ``--out`` writes the
calibration file that ``lrms fit --calibration`` applies; ``--poses separate`` adjusts each
sweep with its own unknown rig pose (the rig or the artefact moved between sweeps); ``--upload
URL`` posts it to a service
(``POST /api/v1/calibrations/upload``, the admin token from ``--token`` or ``$LRMS_ADMIN_TOKEN``). See
docs/calibration.md.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

HELP = "calibrate the rig from sweeps of a room and reference spheres (writes a calibration file)"


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "clouds", nargs="+", metavar="CLOUD", help="calibration sweep(s): cloud .xyz/.txt/.csv/.ply or raw log .mcap"
    )
    parser.add_argument("--artefact", required=True, metavar="ARTEFACT.json", help="planes, spheres, distances")
    parser.add_argument("--out", metavar="CAL.json", default=None, help="write the calibration here")
    parser.add_argument("--json", action="store_true", help="print the whole result as JSON")
    parser.add_argument("--p", type=float, default=0.1, help="nominal inner parameter p of the clouds' mapping, m")
    parser.add_argument(
        "--poses",
        choices=("shared", "separate"),
        default="shared",
        help="shared: the sweeps were taken from one rig pose (default); separate: the rig (or the whole artefact) "
        "moved between sweeps, each sweep gets its own unknown pose (registered by three or more common spheres)",
    )
    parser.add_argument(
        "--plane-points",
        type=int,
        default=20000,
        help="beams per plane (and per pose) the adjustment uses, a random subset (default 20000)",
    )
    parser.add_argument(
        "--sigma-l-mm",
        type=float,
        default=None,
        help="range noise (default: the [noise] of the rig that recorded the raw logs, as the service's calibration "
        "sweep uses it, when they agree; else 11.67 mm, seed 003)",
    )
    parser.add_argument(
        "--optics",
        choices=("ideal", "lms1xx"),
        default="ideal",
        help="the scanner's beam: ideal (thin, default) or lms1xx (8 mm + 15 mrad spot: the spot scale is estimated "
        "from the reference spheres and stored as the calibration's optics)",
    )
    parser.add_argument(
        "--upload", metavar="URL", default=None, help="post the calibration to this service (base URL or the endpoint)"
    )
    parser.add_argument("--token", default=None, help="admin token for --upload (default: $LRMS_ADMIN_TOKEN)")
    parser.add_argument("--name", default="", help="name of the uploaded calibration")
    parser.add_argument("--comment", default="", help="comment of the uploaded calibration")
    parser.add_argument("--activate", action="store_true", help="make the uploaded calibration the rig's active one")


def run(args: argparse.Namespace) -> int:
    import numpy as np

    from lrms.calibration import (
        AdjustOptions,
        Artefact,
        ArtefactError,
        CalibrationError,
        CalibrationOptions,
        Observations,
        calibrate,
    )
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
    nominal: RigModel | None = None
    logged_noise: list[dict[str, float]] = []
    for name in args.clouds:
        if name.lower().endswith(".mcap"):
            from service.replay import log_readings

            r = log_readings(name)
            if nominal is not None and nominal != r.model:
                raise CalibrationError(f"{name}: recorded with another rig model than the sweeps before it")
            nominal = r.model
            if r.noise is not None:
                logged_noise.append(r.noise)
            sweeps.append(Observations.from_raw(r.l, r.alpha, r.beta, r.omega, source=name))
        else:
            sweeps.append(Observations.from_points(read_points(name), args.p, source=name))
    if nominal is None:
        nominal = RigModel(p=args.p)
    elif len(sweeps) > sum(n.lower().endswith(".mcap") for n in args.clouds) and not nominal.is_nominal(args.p):
        raise CalibrationError(
            "clouds (mapped with the nominal Eq. 1, --p) and raw logs recorded with another rig model cannot be mixed"
        )
    if args.sigma_l_mm is not None:
        noise = NoiseModel(sigma_l=args.sigma_l_mm / 1e3)
    elif logged_noise and len(logged_noise) == len(args.clouds) and all(n == logged_noise[0] for n in logged_noise):
        noise = NoiseModel(**logged_noise[0])  # the recording rig's [noise], as its service adjusted with it
    else:
        noise = NoiseModel()
    if args.plane_points < 100:
        raise CalibrationError(f"--plane-points must be at least 100, got {args.plane_points}")
    from lrms.cylinder import BeamOptics

    options = CalibrationOptions(
        adjust=AdjustOptions(max_plane_points=args.plane_points),
        optics=BeamOptics() if args.optics == "lms1xx" else None,
    )
    result = calibrate(sweeps, artefact, nominal=nominal, noise=noise, options=options, poses=args.poses)
    if args.out:
        Path(args.out).write_text(result.to_json() + "\n", encoding="utf-8")
    if args.json:
        sys.stdout.write(result.to_json() + "\n")
    else:
        _print_text(result.to_dict(), args.out)
    if args.upload:
        stored = upload(result.to_json(indent=None), args.upload, args.token, args.name, args.comment, args.activate)
        print(
            f"calibration stored as {stored['id']}" + (" (active)" if stored.get("active") else ""),
            file=sys.stderr if args.json else sys.stdout,
        )
    return 0


def upload(body: str, url: str, token: str | None, name: str, comment: str, activate: bool) -> dict[str, Any]:
    """POST a calibration's JSON to a service: ``url`` is the service's base URL or its
    ``/api/v1/calibrations`` (or ``.../upload``) endpoint. The equivalent curl line::

        curl -X POST -H "Authorization: Bearer $LRMS_ADMIN_TOKEN" -H "Content-Type: application/json" \\
             --data @cal.json "http://127.0.0.1:8000/api/v1/calibrations/upload?name=room-2026-05&activate=true"
    """
    import os

    import httpx

    from service.config import TOKEN_ENVS
    from service.errors import ServiceError

    endpoint = url.rstrip("/")
    if endpoint.endswith("/api/v1/calibrations"):
        endpoint += "/upload"
    elif not endpoint.endswith("/api/v1/calibrations/upload"):
        endpoint += "/api/v1/calibrations/upload"
    tok = token or os.environ.get(TOKEN_ENVS["admin"])
    headers = {"Content-Type": "application/json"}
    if tok:
        headers["Authorization"] = f"Bearer {tok}"
    params: dict[str, str] = {"name": name, "comment": comment, "activate": "true" if activate else "false"}
    try:
        r = httpx.post(endpoint, content=body, headers=headers, params=params, timeout=60.0)
    except httpx.HTTPError as exc:
        raise ServiceError(f"cannot upload the calibration to {endpoint}: {exc}") from None
    if r.status_code != 201:
        try:
            detail = r.json()
            why = detail.get("message") or detail.get("detail")
        except ValueError:
            why = r.text[:200]
        raise ServiceError(f"the service refused the calibration ({r.status_code}): {why}")
    out: dict[str, Any] = r.json()
    return out


def _print_text(d: dict[str, Any], out: str | None) -> None:
    import numpy as np

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
    for pose in d.get("poses", []):
        t = pose["world_from_rig"]
        rot = pose["std_rotation_rad"]
        tr = pose["std_translation_m"]
        print(
            f"pose of sweep {pose['sweep'] + 1}: translation ({t[0][3]:.4f}, {t[1][3]:.4f}, {t[2][3]:.4f}) m"
            + (
                f" (std {1e3 * max(tr):.3f} mm, rotation std {np.rad2deg(max(rot)):.4f} deg)"
                if pose["sweep"]
                else " (the world: held)"
            )
        )
    if d.get("optics"):
        o = d["optics"]
        print(
            f"spot scale from the spheres: {o['spot_scale']:.3f} (u {o['spot_scale_u']:.3f}) x the nominal spot"
            f" ({1e3 * o['exit_diameter_m']:.3g} mm, {1e3 * o['divergence_rad']:.3g} mrad"
            + (f", cut at {o['extent']:.3g} spot radii)" if "extent" in o else ", an endless Gaussian)")
            + (f"; the rig was adjusted with {o['assumed_scale']:.3f}" if "assumed_scale" in o else "")
        )
    if out:
        print(f"calibration written to {out}")
