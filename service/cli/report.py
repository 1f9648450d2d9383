"""``lrms report ID``: a measurement's report (HTML, or PDF with ``--pdf``) from a running service
(the standard-library client :mod:`service.cli._http`, shared with ``lrms measure --server``)."""

from __future__ import annotations

import argparse
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
    from service.cli._http import ApiClient, token_from

    kind = "pdf" if args.pdf else "html"
    client = ApiClient(args.url, token_from(args.token, TOKEN_VARS), args.timeout)
    path = f"/api/v1/measurements/{args.id}/report.{kind}"
    out = args.out or f"report-{args.id}.{kind}"
    if out == "-":
        sys.stdout.buffer.write(client.read(path))
        sys.stdout.buffer.flush()
    else:
        client.download(path, out)
        print(out)
    return 0
