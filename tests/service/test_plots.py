"""The figures of ``service.plots`` written through the commands that draw them."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from service.cli.main import main
from service.pointio import write_xyz


def test_lrms_fit_elbow_draws_the_fit(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from sim.scene.joints import make_joint

    joint = make_joint("a", noise=0.0005, rng=np.random.default_rng(0))
    f = tmp_path / "elbow.xyz"
    write_xyz(f, joint.points)
    png = tmp_path / "elbow.png"
    assert main(["fit", str(f), "--model", "elbow", "--json", "--plot", str(png)]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["plot"] == str(png) and png.read_bytes()[:4] == b"\x89PNG"
