"""``lrms report ID``: a measurement's report (HTML, or PDF with ``--pdf``) from a running service."""

from __future__ import annotations

import argparse
import os
import sys

HELP = "fetch a measurement's report (HTML or PDF) from the service"
DEFAULT_URL = "http://127.0.0.1:8000"
#: Environment variables tried for the bearer token when ``--token`` is not given, in this order.
TOKEN_VARS = ("LRMS_READ_TOKEN", "LRMS_OPERATOR_TOKEN", "LRMS_ADMIN_TOKEN")


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("id", help="measurement id")
    parser.add_argument("--pdf", action="store_true", help="the PDF instead of the HTML page")
    parser.add_argument(
        "--out", metavar="FILE", help="where to write it (default: report-ID.html / .pdf here; '-' = stdout)"
    )
    parser.add_argument("--url", default=DEFAULT_URL, help=f"the service's base URL (default {DEFAULT_URL})")
    parser.add_argument(
        "--token", help=f"bearer token for reads (default: ${', $'.join(TOKEN_VARS)}, the first one set)"
    )
    parser.add_argument("--timeout", type=float, default=120.0, help="seconds to wait for the service (default 120)")


def run(args: argparse.Namespace) -> int:
    import httpx

    from service.errors import ServiceError

    kind = "pdf" if args.pdf else "html"
    token = args.token or next((os.environ[v] for v in TOKEN_VARS if os.environ.get(v)), None)
    headers = {"Authorization": f"Bearer {token}"} if token else {}
    url = f"{args.url.rstrip('/')}/api/v1/measurements/{args.id}/report.{kind}"
    try:
        r = httpx.get(url, headers=headers, timeout=args.timeout)
    except httpx.HTTPError as exc:
        raise ServiceError(f"cannot reach the service at {args.url}: {exc}") from None
    if r.status_code != 200:
        try:
            body = r.json()
            detail = body.get("message") or body.get("detail")
        except ValueError:
            detail = r.text[:200]
        raise ServiceError(f"the service answered {r.status_code}: {detail}")
    out = args.out or f"report-{args.id}.{kind}"
    if out == "-":
        sys.stdout.buffer.write(r.content)
        sys.stdout.buffer.flush()
    else:
        with open(out, "wb") as f:
            f.write(r.content)
        print(out)
    return 0
