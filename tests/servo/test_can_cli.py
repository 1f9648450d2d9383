"""``lrms motor`` in-process against ``sim://`` (argument handling, config file, errors)."""

from __future__ import annotations

from pathlib import Path

import pytest

from service.cli.main import main
from service.cli.motor import _passive


def status_lines(out: str) -> dict[str, str]:
    return dict(line.split(": ", 1) for line in out.strip().splitlines())


def test_move_with_config_file(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    config = tmp_path / "rig.toml"
    config.write_text('[motor]\nurl = "sim://"\ncounts_per_rev = 131072\ngear_ratio = 100\nvelocity_deg_s = 30\n')
    assert main(["motor", "--motor", "sim://?node=3", "--config", str(config), "move", "-2.5"]) == 0
    lines = status_lines(capsys.readouterr().out)
    assert lines["state"].startswith("Operation enabled")
    assert float(lines["position_deg"]) == pytest.approx(-2.5, abs=0.01)
    assert lines["fault"] == "none"


def test_home_and_jog_then_status(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["motor", "--motor", "sim://", "home"]) == 0
    assert float(status_lines(capsys.readouterr().out)["position_deg"]) == pytest.approx(0.0, abs=1e-6)
    assert main(["motor", "--motor", "sim://", "--acceleration", "300", "jog", "5"]) == 0
    assert status_lines(capsys.readouterr().out)["state"].startswith("Operation enabled")


def test_errors_are_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bad = tmp_path / "bad.toml"
    bad.write_text("[motor]\ngear_ratio = 0\n")
    assert main(["motor", "--motor", "sim://", "--config", str(bad), "status"]) == 1
    assert capsys.readouterr().err.startswith("error: gear_ratio must be finite and non-zero")
    assert main(["motor", "--motor", "sim://", "--velocity", "1000", "move", "1"]) == 1
    assert "exceeds the configured maximum" in capsys.readouterr().err
    assert main(["motor", "--motor", "canopen+virtual://nobody?node=4&sdo_timeout=0.05", "status"]) == 1
    assert "no SDO answer" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["motor", "--motor", "sim://", "move"])


def test_status_joins_canopen_passively() -> None:
    assert _passive("canopen+virtual://x?node=1") == "canopen+virtual://x?node=1&setup=0&sync_hz=0"
    assert _passive("canopen+virtual://x") == "canopen+virtual://x?setup=0&sync_hz=0"
    assert _passive("canopen+virtual://x?sync_hz=100") == "canopen+virtual://x?sync_hz=100&setup=0"
    assert _passive("sim://?node=1") == "sim://?node=1"
