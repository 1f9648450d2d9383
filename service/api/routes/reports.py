"""Reports of a measurement (``/api/v1/measurements/{id}/report.html`` and ``report.pdf``) and the
engineer's web page at ``/`` (static HTML + JavaScript from ``service/web``, no build step).

A report is rendered when asked for (service.report): the raw log's SHA-256 is read from the file
at that moment, so a report never vouches for a file that has gone. The routes are plain ``def``:
FastAPI runs them on its thread pool, so drawing the fit plot and the PDF does not block the event
loop.
"""

from __future__ import annotations

from pathlib import Path

from fastapi import APIRouter, FastAPI, HTTPException
from fastapi.responses import FileResponse, HTMLResponse, Response
from fastapi.staticfiles import StaticFiles

from service import report
from service.api.deps import READ, READ_RESPONSES, ServiceDep
from service.api.errors import responses
from service.api.routes.measurements import MeasurementId
from service.store import Measurement

router = APIRouter(prefix="/measurements", tags=["reports"], dependencies=READ, responses=READ_RESPONSES)

WEB_DIR = Path(__file__).resolve().parents[2] / "web"
WEB_ASSETS_URL = "/ui"

_REPORT_RESPONSES = responses(404, 409, 422)


def _reportable(service: ServiceDep, mid: str) -> Measurement:
    m = service.store.get(mid)  # 404 for an unknown id
    if m.request.get("target") == "calibration":
        cid = (m.result or {}).get("calibration_id")
        where = f": its calibration is /api/v1/calibrations/{cid}" if cid else ""
        raise HTTPException(409, f"measurement {mid} is a calibration sweep: no part report{where}")
    if m.state not in report.REPORTABLE:
        why = "it was cancelled and has no result" if m.state == "cancelled" else "wait until it is done"
        raise HTTPException(409, f"measurement {mid} is {m.state}: no report yet ({why})")
    return m


@router.get(
    "/{mid}/report.html",
    response_class=Response,  # not HTMLResponse: its media type would be given to the JSON error bodies
    responses={200: {"content": {"text/html": {}}}, **_REPORT_RESPONSES},
)
def get_report_html(mid: MeasurementId, service: ServiceDep) -> HTMLResponse:
    """The measurement's report as one self-contained HTML page (done or failed measurements)."""
    m = _reportable(service, mid)
    return HTMLResponse(report.render_html(m, service.config))


@router.get(
    "/{mid}/report.pdf",
    response_class=Response,
    responses={200: {"content": {"application/pdf": {}}}, **_REPORT_RESPONSES},
)
def get_report_pdf(mid: MeasurementId, service: ServiceDep) -> Response:
    """The same report as PDF (rendered from the same HTML by WeasyPrint)."""
    m = _reportable(service, mid)
    pdf = report.render_pdf(m, service.config)
    return Response(
        pdf, media_type="application/pdf", headers={"Content-Disposition": f'inline; filename="report-{mid}.pdf"'}
    )


def mount_web(app: FastAPI) -> None:
    """The engineer's page at ``/`` and its script and style sheet under ``/ui`` (open: the page
    holds no data; it reads the API with the token typed into it when reads need one)."""
    app.mount(WEB_ASSETS_URL, StaticFiles(directory=WEB_DIR), name="web")

    @app.get("/", include_in_schema=False)
    async def index() -> FileResponse:
        return FileResponse(WEB_DIR / "index.html", media_type="text/html")
