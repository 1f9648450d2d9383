"""Across processes: ``lrms sim motor`` serves the simulated Modbus drive on a pty, ``lrms motor`` drives it."""

from __future__ import annotations

import signal
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
LRMS = [sys.executable, "-m", "service.cli.main"]


def lrms(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([*LRMS, *args], cwd=REPO, capture_output=True, text=True, timeout=60)


def field(out: str, name: str) -> str:
    for line in out.splitlines():
        if line.startswith(name + ":"):
            return line.split(":", 1)[1].strip()
    raise AssertionError(f"no {name!r} in {out!r}")


def test_sim_motor_and_motor_commands_over_a_pty(tmp_path: Path) -> None:
    link = tmp_path / "servo"
    sim = subprocess.Popen(
        [*LRMS, "sim", "motor", "--motor", f"modbus-rtu://{link}?unit=3"],
        cwd=REPO,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        assert sim.stdout is not None
        first = sim.stdout.readline().strip()
        assert first == f"serving modbus-rtu://{link}?unit=3", first + (sim.stderr.read() if sim.poll() else "")
        url = first.removeprefix("serving ")
        assert link.is_symlink()

        out = lrms("motor", "--motor", url, "status")
        assert out.returncode == 0, out.stderr
        assert field(out.stdout, "state").startswith("Switch on disabled")
        assert field(out.stdout, "fault") == "none"

        out = lrms("motor", "--motor", url, "move", "4.5")
        assert out.returncode == 0, out.stderr
        assert field(out.stdout, "state").startswith("Operation enabled")
        assert float(field(out.stdout, "position_deg")) == pytest.approx(4.5, abs=0.011)

        out = lrms("motor", "--motor", url, "disable")  # a new process finds the drive where the last one left it
        assert out.returncode == 0, out.stderr
        assert field(out.stdout, "state").startswith("Ready to switch on")
        assert float(field(out.stdout, "position_deg")) == pytest.approx(4.5, abs=0.011)

        out = lrms("motor", "--motor", f"modbus-rtu://{link}?unit=4&timeout=0.05", "status")  # nobody answers unit 4
        assert out.returncode == 1
        assert out.stderr.startswith("error:") and "no reply" in out.stderr
    finally:
        sim.send_signal(signal.SIGINT)
        try:
            sim.wait(timeout=10)
        finally:
            if sim.poll() is None:
                sim.kill()
    assert sim.returncode == 0
    assert not link.exists()
