"""``lrms sim scanner`` as a separate process: it prints its address and serves real TCP until Ctrl-C."""

from __future__ import annotations

import re
import signal
import subprocess
import sys
from collections.abc import Callable

import numpy as np
import pytest

from drivers.lms100 import DeviceIdent, ErrorReply, PollScan, RawTelegram, ReadDeviceIdent, ScanDataReply
from tests.conftest import REPO
from tests.sim.conftest import Link

CLI = [sys.executable, "-m", "service.cli.main", "sim", "scanner"]


@pytest.mark.parametrize("sensor", ["ideal", "lms1xx"])
def test_cli_serves_until_interrupted(connect: Callable[..., Link], sensor: str) -> None:
    proc = subprocess.Popen(
        [*CLI, "--port", "0", "--cola", "a", "--scene", "wall", "--fast", "--sensor", sensor],
        cwd=REPO,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        assert proc.stdout is not None
        line = proc.stdout.readline()
        m = re.search(r"tcp://(127\.0\.0\.1):(\d+)\?cola=a", line)
        assert m, line
        assert f"sensor={sensor}" in line
        link = connect((m.group(1), int(m.group(2))), "a")
        assert link.request(ReadDeviceIdent()) == DeviceIdent("LMS10x_FieldEval", "V1.36-21.10.2010")
        polled = link.request(PollScan())
        assert isinstance(polled, ScanDataReply)
        ahead = np.abs(polled.scan.angles_rad - np.pi / 2) < np.deg2rad(1)
        assert np.all(np.abs(polled.scan.ranges_m[ahead] - 3.0) < 0.08)  # the wall 3 m ahead
        assert link.request(RawTelegram("sRN", "LFPmeanfilter")) == ErrorReply(3)
        link.close()
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=20)
        assert proc.returncode == 0, err
        # the rejected request is logged on stderr with its reason
        assert re.search(r"WARNING sim\.scanner\.device: simulated LMS100 rejected .*LFPmeanfilter.*not simulated", err)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()


def test_cli_lists_scenes_and_rejects_unknown_ones() -> None:
    out = subprocess.run([*CLI, "--list-scenes"], cwd=REPO, capture_output=True, text=True, timeout=60)
    assert out.returncode == 0 and "seed003" in out.stdout and "wall" in out.stdout
    bad = subprocess.run([*CLI, "--port", "0", "--scene", "nope"], cwd=REPO, capture_output=True, text=True, timeout=60)
    assert bad.returncode == 1 and bad.stderr.startswith("error:") and "unknown scene" in bad.stderr
