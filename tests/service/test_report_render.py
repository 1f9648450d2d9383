"""Reports rendered from results built by hand with the keys of the recipe work (part, thermal,
decision, calibration): every section, the tolerance drawing, omitted sections, the raw log's
hash or its absence, failed and unfinished measurements, and the PDF read back with pypdf."""

from __future__ import annotations

import hashlib
import html as htmllib
import io
import re
import time
from pathlib import Path
from typing import Any

import pytest

from lrms import __version__
from service.config import RigConfig, parse_toml
from service.errors import ServiceError
from service.report import ReportNotReady, html_to_pdf, raw_log_info, render_html, render_pdf, tolerance_zone
from service.store import Measurement

CFG: RigConfig = parse_toml("[sim]\n")


def _row(source: str, u_m: float, unit: str = "m") -> dict[str, Any]:
    return {
        "source": source,
        "type": "B",
        "u_x": u_m,
        "unit": unit,
        "c": 1.0,
        "u_m": u_m,
        "distribution": "normal",
        "note": f"note of {source}",
    }


def full_result(outcome: str = "conforms") -> dict[str, Any]:
    return {
        "model": "cylinder",
        "diameter_m": 0.32551,
        "rmse_m": 0.0004,
        "n_points": 5120,
        "uncertainty": {
            "budget": [dict(_row("fit (type A)", 1.2e-4), type="A"), _row("range offset", 2.5e-4)],
            "combined_m": 2.774e-4,
            "expanded_m": 5.548e-4,
            "k": 2.0,
        },
        "part": {"recipe": "FLANGE-SHAFT-320", "recipe_version": 3, "part_id": "PART-4711", "operator": "kim"},
        "thermal": {
            "material": "C45 (carbon steel)",
            "part_temperature_c": 1050.0,
            "temperature_uncertainty_c": 15.0,
            "diameter_measured_m": 0.32551,
            "diameter_20c_m": 0.32050,
            "u_thermal_m": 1.9e-4,
            "budget": [
                _row("part temperature", 15.0, "K") | {"c": 1.2e-5, "u_m": 1.8e-4},
                _row("expansion data", 6e-5),
            ],
        },
        "decision": {
            "rule": "ISO 14253-1 guard band",
            "outcome": outcome,
            "value_m": 0.32050,
            "lsl_m": 0.3195,
            "usl_m": 0.3215,
            "expanded_m": 6.6e-4,
            "k": 2.0,
            "acceptance_zone_m": [0.32016, 0.32084],
            "note": "inside the tolerance shrunk by U",
        },
        "calibration": {"id": "cal-0042", "name": "bay-3 spring", "created": "2026-11-01T08:00:00Z"},
    }


def measurement(
    result: dict[str, Any] | None,
    raw: Path | None,
    state: str = "done",
    error: str | None = None,
) -> Measurement:
    return Measurement(
        "0123456789abcdef",
        1.79e9,
        1.79e9 + 1,
        1.79e9 + 20,
        state,
        {"target": "cylinder"},
        1.0,
        state,
        result,
        error,
        None if raw is None else str(raw),
        None,
        None,
    )


def text_of(html: str) -> str:
    return re.sub(r"\s+", " ", htmllib.unescape(re.sub(r"<[^>]+>", " ", html)))


def test_every_section_of_a_full_result(tmp_path: Path) -> None:
    raw = tmp_path / "0123456789abcdef.mcap"
    raw.write_bytes(b"\x89MCAP0\r\n" + bytes(range(256)) * 40)
    digest = hashlib.sha256(raw.read_bytes()).hexdigest()
    html = render_html(measurement(full_result(), raw), CFG)
    text = text_of(html)
    # part and recipe version
    assert "PART-4711" in text and "FLANGE-SHAFT-320, version 3" in text and "kim" in text
    # measured (hot) and 20 C values, thermal correction
    assert "325.510 mm" in text and "320.500 mm" in text and "C45 (carbon steel)" in text
    assert "1050.0 C ± 15.0 C" in text
    # the decision and its drawing: LSL, USL, acceptance zone, the value with its +-U bar
    assert 'class="outcome conforms"' in html and "ISO 14253-1 guard band" in text
    assert "LSL 319.500" in html and "USL 321.500" in html and 'class="acceptance"' in html
    assert "320.500 &#177; 0.660 mm" in html
    # budget: the measurement's rows and the thermal rows, in micrometres
    budget = html.split('id="budget"')[1].split("</table>")[0]
    for source, um in (
        ("fit (type A)", "120.0"),
        ("range offset", "250.0"),
        ("part temperature", "180.0"),
        ("expansion data", "60.0"),
    ):
        assert source in budget and um in budget
    assert budget.count('class="thermal"') == 2
    # traceability: calibration, software version, the raw log's name and hash
    assert "id: cal-0042; name: bay-3 spring; created: 2026-11-01T08:00:00Z" in text
    assert f"lrms {__version__}" in text
    assert f"0123456789abcdef.mcap ({raw.stat().st_size} bytes)" in text and f"SHA-256 {digest}" in text
    # no cloud: the fit section says why instead of an image
    assert "No fit plot: no cloud was recorded." in text and "<img" not in html
    assert "raw log missing" not in text and "Failure" not in text


@pytest.mark.parametrize("outcome", ["does_not_conform", "cannot_decide"])
def test_other_outcomes_are_named(outcome: str, tmp_path: Path) -> None:
    html = render_html(measurement(full_result(outcome), None), CFG)
    assert f'class="outcome {outcome}"' in html and outcome.replace("_", " ") in html


def test_sections_absent_from_the_result_are_left_out() -> None:
    r = full_result()
    for key in ("part", "thermal", "decision", "calibration"):
        del r[key]
    html = render_html(measurement(r, None), CFG)
    text = text_of(html)
    assert "<svg" not in html and "Conformity decision" not in text and "Thermal correction" not in text
    assert ">Part<" not in html and "diameter at 20 C" not in text
    assert "calibration not recorded in the result" in text
    assert "fit (type A)" in text and "thermal" not in html.split('id="budget"')[1]
    # a result that says "no calibration" (null) says so
    html = render_html(measurement({**r, "calibration": None}, None), CFG)
    assert "none (nominal kinematics, uncalibrated budget)" in html


def test_raw_log_missing(tmp_path: Path) -> None:
    gone = tmp_path / "gone.mcap"
    text = text_of(render_html(measurement(full_result(), gone), CFG))
    assert "gone.mcap: raw log missing" in text and "SHA-256" not in text
    text = text_of(render_html(measurement(full_result(), None), CFG))
    assert "raw log missing (none was recorded)" in text
    assert raw_log_info(None).status == "none" and raw_log_info(str(gone)).status == "missing"


def test_failed_measurement_states_the_failure() -> None:
    reason = "motor fault 0x8130: heartbeat lost"
    text = text_of(render_html(measurement(None, None, "failed", reason), CFG))
    assert "The measurement failed; it has no valid result." in text and reason in text
    assert "No fit plot" not in text and "Uncertainty budget" not in text


@pytest.mark.parametrize("state", ["queued", "running", "cancelled"])
def test_no_report_before_the_end(state: str) -> None:
    with pytest.raises(ReportNotReady, match=f"is {state}"):
        render_html(measurement(None, None, state), CFG)


def test_tolerance_zone_geometry() -> None:
    z = tolerance_zone(full_result()["decision"])
    assert z is not None
    assert z["left"] < z["tol"][0] < z["acc"][0] < z["value_x"] < z["acc"][1] < z["tol"][1] < z["right"]
    assert z["bar"][0] < z["value_x"] < z["bar"][1]
    assert z["value_x"] - z["bar"][0] == pytest.approx(z["bar"][1] - z["value_x"])
    # a one-sided tolerance (no LSL): the tolerance and acceptance zone run to the left edge
    one = dict(full_result()["decision"], lsl_m=None, acceptance_zone_m=[None, 0.32084])
    z1 = tolerance_zone(one)
    assert z1 is not None and z1["tol"][0] == z1["acc"][0] == z1["left"] and z1["lsl_x"] is None
    assert tolerance_zone({"outcome": "cannot_decide", "value_m": None}) is None


def test_pdf_has_the_same_content(tmp_path: Path) -> None:
    import pypdf

    raw = tmp_path / "run.mcap"
    raw.write_bytes(b"raw log bytes")
    digest = hashlib.sha256(b"raw log bytes").hexdigest()
    pdf = render_pdf(measurement(full_result(), raw), CFG)
    assert pdf.startswith(b"%PDF-")
    reader = pypdf.PdfReader(io.BytesIO(pdf))
    text = "".join(page.extract_text() for page in reader.pages)
    flat = re.sub(r"\s+", "", text)
    assert "PART-4711" in text and digest in flat and "conforms" in text and "rangeoffset" in flat


def test_pdf_loads_nothing_from_outside() -> None:
    """Only data: URLs: a report page pointing at a network or file image is refused
    (WeasyPrint's fetcher refuses the URL, fatally: a report is never silently incomplete)."""
    with pytest.raises(ServiceError, match=re.escape("disallowed protocol: http://127.0.0.1:9/x.png")):
        html_to_pdf('<html><body><img src="http://127.0.0.1:9/x.png"></body></html>')


def test_failed_measurement_report_over_http_needs_a_read_token(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A measurement that fails has a report saying so (HTML and PDF); reads need the token when
    ``[auth] read = "token"``; the engineer's page itself is open."""
    import httpx

    from service.api import ServerThread, Service, create_app
    from service.config import TOKEN_ENV, TOKEN_ENVS
    from service.jobs import JobContext

    for var in (TOKEN_ENV, *TOKEN_ENVS.values()):
        monkeypatch.delenv(var, raising=False)

    def measure(ctx: JobContext) -> dict[str, Any]:
        raise ServiceError("scanner link lost during the sweep")

    toml = f"[sim]\n[storage]\ndir = '{tmp_path}'\n[auth]\nread = 'token'\noperator_token = 'op'\nread_token = 'rd'\n"
    svc = Service(parse_toml(toml), measure)
    with ServerThread(create_app(svc)) as srv, httpx.Client(base_url=srv.url, timeout=60) as c:
        mid = c.post("/api/v1/measurements", json={"target": "cylinder"}, headers={"Authorization": "Bearer op"})
        mid = mid.json()["id"]
        end = time.monotonic() + 20
        while c.get(f"/api/v1/measurements/{mid}", headers={"Authorization": "Bearer rd"}).json()["state"] != "failed":
            assert time.monotonic() < end
            time.sleep(0.02)
        assert c.get(f"/api/v1/measurements/{mid}/report.html").status_code == 401
        r = c.get(f"/api/v1/measurements/{mid}/report.html", headers={"Authorization": "Bearer rd"})
        assert r.status_code == 200
        text = text_of(r.text)
        assert "The measurement failed; it has no valid result." in text
        assert "scanner link lost during the sweep" in text
        r = c.get(f"/api/v1/measurements/{mid}/report.pdf", headers={"Authorization": "Bearer rd"})
        assert r.status_code == 200 and r.content.startswith(b"%PDF-")
        page = c.get("/")
        assert page.status_code == 200 and page.headers["content-type"].startswith("text/html")
        assert '<script src="/ui/app.js"' in page.text
        assert "fetch(" in c.get("/ui/app.js").text and c.get("/ui/style.css").status_code == 200


def test_a_fit_flagged_outside_its_nominal_range_says_so() -> None:
    """The request's nominal diameter range in the measured values, and the flag of a fit outside
    it within 3 u (``diameter_range_excess_m`` / ``_u``) as a warning row; none inside it."""
    r = full_result("cannot_decide") | {
        "diameter_range_m": [0.2925, 0.3225],
        "diameter_range_excess_m": 0.00301,
        "diameter_range_excess_u": 1.46,
    }
    text = text_of(render_html(measurement(r, None), CFG))
    assert "nominal diameter range of the request 292.500 mm .. 322.500 mm" in text
    assert "warning: outside the nominal range by +3.010 mm (1.46 u of the fit)" in text
    inside = r | {"diameter_range_excess_m": None, "diameter_range_excess_u": None}
    text = text_of(render_html(measurement(inside, None), CFG))
    assert "nominal diameter range of the request" in text and "outside the nominal range" not in text
