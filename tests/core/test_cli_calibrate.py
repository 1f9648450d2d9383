"""``lrms calibrate`` and ``lrms fit --calibration`` end to end on simulated clouds written to files."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from lrms import kinematics as k
from service.cli.main import main
from service.pointio import write_xyz
from sim.scene import SEED003_DIAMETER, SensorModel, cast_beams, continuous_sweep_cloud, get_scene
from sim.scene.library import room_spheres_artefact

D = np.deg2rad
RIG = k.RigModel(k0=0.025, p=0.1035, q=0.003, tilt_x=D(0.25), alpha_zero=D(0.12), beta_scale=300e-6)


def nominal_cloud(scene: str, rig: k.RigModel, sensor: SensorModel, lo: float, hi: float, speed: float) -> np.ndarray:
    """What today's software writes: the sweep of the true ``rig`` mapped with the nominal Eq. 1."""
    cal = k.RigCalibration(model=rig)
    _, s = continuous_sweep_cloud(get_scene(scene), cal, sensor, D(lo), D(hi), D(speed), rng=np.random.default_rng(1))
    v = s.valid
    return k.forward(s.ranges[v], cal.alpha(s.device_angle[v]), cal.beta(s.motor_angle[v]))


@pytest.fixture(scope="module")
def files(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    d = tmp_path_factory.mktemp("cal")
    room = d / "room.xyz"
    write_xyz(room, nominal_cloud("room-spheres", RIG, SensorModel(), -90, 90, 10))
    art = d / "artefact.json"
    art.write_text(json.dumps(room_spheres_artefact()))
    return {"room": room, "artefact": art, "dir": d}


def test_calibrate_writes_a_calibration_that_fit_applies(
    files: dict[str, Path], capsys: pytest.CaptureFixture[str]
) -> None:
    out = files["dir"] / "cal.json"
    assert (
        main(["calibrate", str(files["room"]), "--artefact", str(files["artefact"]), "--out", str(out), "--json"]) == 0
    )
    printed = json.loads(capsys.readouterr().out)
    stored = json.loads(out.read_text())
    assert printed["model"] == stored["model"]
    assert abs(stored["model"]["k0"] - RIG.k0) < 3 * stored["std"]["k0"]
    assert "beta_zero" in stored["identifiability"]["held"]
    # the part, swept by the same rig without noise: before and after the calibration
    dev = np.deg2rad(np.arange(60.0, 120.0, 0.25))
    mot = D(np.arange(-35.0, 75.0, 0.4))[:, None]
    cal = k.RigCalibration(model=RIG)
    s = cast_beams(get_scene("seed003-bare"), cal, SensorModel.noiseless(), dev, mot)
    on = s.valid & (s.index == 0)
    pts = k.forward(
        s.ranges[on], cal.alpha(np.broadcast_to(dev, on.shape)[on]), cal.beta(np.broadcast_to(mot, on.shape)[on])
    )
    part = files["dir"] / "part.xyz"
    write_xyz(part, pts)
    assert main(["fit", str(part), "--json"]) == 0
    before = json.loads(capsys.readouterr().out)
    assert main(["fit", str(part), "--json", "--calibration", str(out)]) == 0
    after = json.loads(capsys.readouterr().out)
    assert after["calibration"]["file"] == str(out)
    tilt_before = np.rad2deg(np.arccos(abs(before["axis_direction"][2])))
    tilt_after = np.rad2deg(np.arccos(abs(after["axis_direction"][2])))
    assert tilt_before > 1.0  # the scan-plane tilt and the others tip the vertical part's axis
    assert tilt_after < 0.05
    # one 10 deg/s calibration sweep leaves k1 at +-270 ppm, p at +-0.08 mm (1 sigma): tenths of a mm
    assert abs(after["diameter_m"] - SEED003_DIAMETER) < 0.4e-3


def test_calibrate_text_output(files: dict[str, Path], capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["calibrate", str(files["room"]), "--artefact", str(files["artefact"])]) == 0
    text = capsys.readouterr().out
    assert "held beta_zero" in text and "k0" in text and "variance factor" in text


def test_bad_artefact_is_an_error_and_nothing_is_written(
    files: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"planes": True, "spheres": [{"diameter_m": -0.2}]}))
    out = tmp_path / "cal.json"
    assert main(["calibrate", str(files["room"]), "--artefact", str(bad), "--out", str(out)]) == 1
    assert "diameter" in capsys.readouterr().err
    assert not out.exists()
    tiny = tmp_path / "tiny.xyz"
    write_xyz(tiny, np.random.default_rng(0).normal(size=(100, 3)) + np.array([0.0, 3.0, 0.0]))
    assert main(["calibrate", str(tiny), "--artefact", str(files["artefact"]), "--out", str(out)]) == 1
    assert "at least" in capsys.readouterr().err
    assert not out.exists()
