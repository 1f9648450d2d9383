"""Measurement reports: one Jinja2 template (``service/templates/report.html``) rendered to HTML,
and the same HTML to PDF by WeasyPrint.

A report holds the part (``result["part"]``), the measured values and the 20 C values
(``result["thermal"]``), the conformity decision with its tolerance zone drawn as inline SVG
(``result["decision"]``), the uncertainty budget (``result["uncertainty"]["budget"]`` and the
thermal rows), the fit plot (:func:`service.plots.plot_measurement`, embedded as a PNG data URI),
the calibration used, the software version and the raw log's file name and SHA-256 (read from the
file when the report is made). Sections whose keys a result lacks are left out; a failed
measurement's report states the failure. Nothing is fetched over a network: the plot is inline,
the fonts are the system's (fontconfig), and the PDF renderer may load ``data:`` URLs only.
"""

from __future__ import annotations

import base64
import datetime as dt
import hashlib
import math
import os
import tempfile
import threading
from dataclasses import dataclass
from functools import cache
from pathlib import Path
from typing import TYPE_CHECKING, Any

from lrms import __version__
from service.config import RigConfig
from service.errors import ServiceError
from service.store import Measurement

if TYPE_CHECKING:
    import jinja2

#: States that have a report (a failed measurement's report states the failure).
REPORTABLE = frozenset({"done", "failed"})

TEMPLATES = Path(__file__).parent / "templates"

_plot_lock = threading.Lock()  # pyplot keeps global state: one figure at a time


class ReportNotReady(ServiceError):
    """The measurement has no report (yet): it is queued, running or was cancelled."""


@dataclass(frozen=True)
class RawLog:
    """The raw log's file name and SHA-256 (``sha256`` None: no log recorded, or the file is gone)."""

    name: str | None
    sha256: str | None
    size: int | None
    status: str  # "ok", "missing" (recorded, file gone), "none" (nothing was recorded)


def raw_log_info(path: str | None) -> RawLog:
    """Hash the raw log at ``path`` (streamed; the file may be large)."""
    if path is None:
        return RawLog(None, None, None, "none")
    name = os.path.basename(path)
    try:
        with open(path, "rb") as f:
            digest = hashlib.file_digest(f, "sha256").hexdigest()
            size = os.fstat(f.fileno()).st_size
    except FileNotFoundError:
        return RawLog(name, None, None, "missing")
    return RawLog(name, digest, size, "ok")


def _finite(x: Any) -> float | None:
    if isinstance(x, bool) or not isinstance(x, int | float):
        return None
    return float(x) if math.isfinite(x) else None


def tolerance_zone(decision: dict[str, Any], width: float = 640.0) -> dict[str, Any] | None:
    """Geometry (SVG user units) of the decision's drawing: the tolerance (LSL..USL), the
    acceptance zone, the value and its +-U bar on one axis in mm. An open side (a null limit)
    runs to the edge. None when the decision has no finite value."""
    value = _finite(decision.get("value_m"))
    if value is None:
        return None
    u = _finite(decision.get("expanded_m")) or 0.0
    lsl, usl = _finite(decision.get("lsl_m")), _finite(decision.get("usl_m"))
    zone = decision.get("acceptance_zone_m") or [None, None]
    acc_lo = _finite(zone[0]) if len(zone) > 0 else None
    acc_hi = _finite(zone[1]) if len(zone) > 1 else None
    pts = [p for p in (value - u, value + u, lsl, usl, acc_lo, acc_hi) if p is not None]
    lo, hi = min(pts), max(pts)
    span = hi - lo or max(abs(value) * 1e-3, 1e-6)
    lo, hi = lo - 0.2 * span, hi + 0.2 * span
    pad = 12.0

    def x(v: float | None, default: float) -> float:
        if v is None:
            return default
        return pad + (v - lo) / (hi - lo) * (width - 2 * pad)

    left, right = pad, width - pad
    return {
        "width": width,
        "height": 130.0,
        "left": left,
        "right": right,
        "tol": (x(lsl, left), x(usl, right)),
        "acc": (x(acc_lo, left), x(acc_hi, right)),
        "lsl_x": None if lsl is None else x(lsl, left),
        "usl_x": None if usl is None else x(usl, right),
        "lsl_mm": None if lsl is None else lsl * 1e3,
        "usl_mm": None if usl is None else usl * 1e3,
        "value_x": x(value, left),
        "bar": (x(value - u, left), x(value + u, right)),
        "value_mm": value * 1e3,
        "u_mm": u * 1e3,
        "outcome": decision.get("outcome", ""),
    }


def fit_plot_png(m: Measurement, config: RigConfig) -> tuple[bytes | None, str]:
    """The fit plot of ``m`` as PNG bytes, or None and why not."""
    from service.plots import plot_measurement

    if m.result is None or m.cloud_path is None:
        return None, "no cloud was recorded"
    if not os.path.isfile(m.cloud_path):
        return None, "the cloud file is missing from storage"
    if "model" not in m.result:
        return None, "the result has no fitted model"
    with tempfile.TemporaryDirectory(prefix="lrms-report-") as tmp, _plot_lock:
        out = Path(tmp) / "fit.png"
        try:
            plot_measurement(m.cloud_path, m.result, config, out)
        except (ServiceError, KeyError, ValueError, OSError) as exc:
            return None, f"the fit plot could not be drawn: {exc}"
        return out.read_bytes(), ""


def _utc(t: float | None) -> str:
    if t is None:
        return "-"
    return dt.datetime.fromtimestamp(t, dt.UTC).strftime("%Y-%m-%d %H:%M:%S UTC")


def _mm(v: Any, digits: int = 3) -> str:
    f = _finite(v)
    return "-" if f is None else f"{f * 1e3:.{digits}f} mm"


def _num(v: Any, fmt: str = ".4g") -> str:
    if v is None:
        return "-"
    f = _finite(v)
    return str(v) if f is None else format(f, fmt)


def _um(v: Any) -> str:
    f = _finite(v)
    return "-" if f is None else f"{f * 1e6:.1f}"


def _deg(v: Any) -> str:
    f = _finite(v)
    return "-" if f is None else f"{f:.3f} deg"


@cache
def _environment() -> jinja2.Environment:
    """The templates' environment, made when the first report is rendered (jinja2 loads then, not
    with the service)."""
    import jinja2

    env = jinja2.Environment(
        loader=jinja2.FileSystemLoader(TEMPLATES),
        autoescape=jinja2.select_autoescape(["html"]),
        undefined=jinja2.StrictUndefined,
        trim_blocks=True,
        lstrip_blocks=True,
    )
    env.filters.update(mm=_mm, num=_num, um=_um, utc=_utc, deg=_deg)
    return env


def _values(result: dict[str, Any]) -> list[tuple[str, str]]:
    """The measured values: (label, text) rows."""
    rows: list[tuple[str, str]] = []
    model = result.get("model")
    if model is not None:
        rows.append(("model", str(model)))
    thermal = result.get("thermal")
    if "diameter_m" in result:
        label = "diameter, measured" + (" (at part temperature)" if thermal else "")
        rows.append((label, _mm(result["diameter_m"])))
    if thermal:
        rows.append(("diameter at 20 C", _mm(thermal.get("diameter_20c_m"))))
    unc = result.get("uncertainty") or {}
    if "expanded_m" in unc:
        rows.append((f"expanded uncertainty U (k = {_num(unc.get('k'), 'g')})", _mm(unc["expanded_m"], 4)))
    if "combined_m" in unc:
        rows.append(("combined standard uncertainty u_c", _mm(unc["combined_m"], 4)))
    if "d_min_m" in unc and "d_max_m" in unc:
        rows.append(("critical-point interval", f"{_mm(unc['d_min_m'])} .. {_mm(unc['d_max_m'])}"))
    rng = result.get("diameter_range_m")
    if isinstance(rng, list | tuple) and len(rng) == 2:
        rows.append(("nominal diameter range of the request", f"{_mm(rng[0])} .. {_mm(rng[1])}"))
        excess = result.get("diameter_range_excess_m")
        if excess is not None:  # the fit outside it, within 3 of its u (lrms.cylinder.nominal_check)
            f = _finite(excess)
            by = "-" if f is None else f"{f * 1e3:+.3f} mm"
            in_u = _num(result.get("diameter_range_excess_u"), ".2f")
            rows.append(("warning: outside the nominal range by", f"{by} ({in_u} u of the fit)"))
    for key, label in (("bend_radius_m", "bend radius A"), ("flange_diameter_m", "flange diameter")):
        if key in result:
            rows.append((label, _mm(result[key])))
    if "degree" in result:
        rows.append(("bend angle", f"{_num(result['degree'], '.3f')} deg"))
    if "rmse_m" in result:
        rows.append(("rms residual", _mm(result["rmse_m"], 4)))
    for key, label in (("n_points", "points fitted"), ("n_inliers", "inliers"), ("points_in_roi", "points in ROI")):
        if key in result:
            rows.append((label, str(result[key])))
    return rows


def report_context(m: Measurement, config: RigConfig, plot: bool = True) -> dict[str, Any]:
    """What the template renders for ``m`` (a done or failed measurement)."""
    if m.state not in REPORTABLE:
        why = "it was cancelled" if m.state == "cancelled" else "it has not finished"
        raise ReportNotReady(f"measurement {m.id} is {m.state}: no report, {why}")
    result = m.result or {}
    png, plot_note = fit_plot_png(m, config) if plot else (None, "not drawn")
    unc = result.get("uncertainty") or {}
    thermal = result.get("thermal") or None
    budget = [dict(r, group="measurement") for r in unc.get("budget") or []]
    if thermal:
        budget += [dict(r, group="thermal") for r in thermal.get("budget") or []]
    decision = result.get("decision") or None
    return {
        "m": m,
        "result": result,
        "part": result.get("part") or None,
        "thermal": thermal,
        "decision": decision,
        "zone": tolerance_zone(decision) if decision else None,
        "values": _values(result),
        "budget": budget,
        "uncertainty": unc,
        "calibration": result.get("calibration"),
        "has_calibration_key": "calibration" in result,
        "raw": raw_log_info(m.raw_path),
        "raw_truncated": m.raw_truncated,
        "plot_uri": None if png is None else "data:image/png;base64," + base64.b64encode(png).decode("ascii"),
        "plot_note": plot_note,
        "version": __version__,
        "generated": _utc(dt.datetime.now(dt.UTC).timestamp()),
        "rig_name": config.name,
    }


def render_html(m: Measurement, config: RigConfig, plot: bool = True) -> str:
    """The report of ``m`` as one self-contained HTML page (:class:`ReportNotReady` when it has none)."""
    return _environment().get_template("report.html").render(**report_context(m, config, plot))


def html_to_pdf(html: str) -> bytes:
    """``html`` (a self-contained report page) as PDF; only ``data:`` URLs may be loaded."""
    import weasyprint

    fetcher = weasyprint.URLFetcher(allowed_protocols={"data"}, fail_on_errors=True)
    try:
        pdf: bytes = weasyprint.HTML(string=html, url_fetcher=fetcher, base_url=None).write_pdf()
    except weasyprint.urls.FatalURLFetchingError as exc:  # a report loads nothing from outside
        raise ServiceError(f"{exc}: {exc.__cause__}") from None
    return pdf


def render_pdf(m: Measurement, config: RigConfig, plot: bool = True) -> bytes:
    """The report of ``m`` as PDF, from the same HTML as :func:`render_html`."""
    return html_to_pdf(render_html(m, config, plot))
