"""The rig TOML: the built-in simulated rig, real rigs, and clear errors for bad files."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from service.config import TOKEN_ENV, load_config, parse_toml
from service.errors import ConfigError

REAL = """
name = "bay-3"
[scanner]
url = "tcp://10.0.0.5:2112?cola=b"
[motor]
url = "canopen+socketcan://can0?node=1"
[kinematics]
p_m = 0.12
motor_zero_deg = 1.5
[storage]
dir = "data"
[auth]
token = "s3cret"
"""


def test_default_rig_is_the_simulated_seed003_rig(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("LRMS_DATA", str(tmp_path))
    cfg = load_config()
    assert cfg.is_sim and cfg.sim is not None and cfg.sim.scene == "seed003"
    assert cfg.scanner.url is None and cfg.motor.url is None
    assert cfg.calibration.p == pytest.approx(0.1)
    assert cfg.noise.sigma_l_m**2 == pytest.approx(136.11e-6, rel=1e-3)
    assert cfg.storage.db_path == tmp_path / "lrms-data" / "lrms.sqlite"
    assert cfg.sweep.mode == "constant" and cfg.sweep.stop_deg > cfg.sweep.start_deg


def test_real_rig_file(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    f = tmp_path / "rig.toml"
    f.write_text(REAL)
    monkeypatch.delenv(TOKEN_ENV, raising=False)
    cfg = load_config(f)
    assert cfg.scanner.url == "tcp://10.0.0.5:2112?cola=b" and not cfg.is_sim
    assert cfg.calibration.motor_zero == pytest.approx(np.deg2rad(1.5))
    assert cfg.storage.dir == tmp_path / "data"  # relative to the file
    assert cfg.api_token() == "s3cret"


def test_token_from_environment(monkeypatch: pytest.MonkeyPatch) -> None:
    cfg = parse_toml(REAL.replace('token = "s3cret"', ""))
    monkeypatch.delenv(TOKEN_ENV, raising=False)
    assert cfg.api_token() is None
    monkeypatch.setenv(TOKEN_ENV, "from-env")
    assert cfg.api_token() == "from-env"


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("[scanner]\nurl='tcp://h:1'\n", "motor"),
        ("[sim]\n[scanner]\nurl='tcp://h:1'\n", "exclusive"),
        ("[sim]\n[scanner]\nurll='x'\n", "scanner.url"),
        ("[sim]\n[sweep]\nspeed_deg_s=-1\n", "sweep.speed_deg_s"),
        ("[sim]\n[sweep]\nstart_deg=5\nstop_deg=5\n", "differ"),
        ("[sim]\n[sweep]\nmode='zigzag'\n", "sweep.mode"),
        ("[sim]\n[kinematics]\np_m=-1\n", "inner parameter"),
        ("[sim]\n[kinematics]\nbogus=1\n", "bogus"),
        ("[sim]\nscene=3\n", "scene"),
        ("[sim]\nsensor='lms2xx'\n", "sensor"),
        ("[sim]\nrig_errors = {range_offset_mm = 1}\n", "unknown rig error"),
        ("[sim]\nrig_errors = {p_m = -0.1}\n", "inner parameter"),
        ("[sim\n", "not valid TOML"),
        ("[scanner]\nurl='10.0.0.5:2112'\n[motor]\nurl='canopen+socketcan://can0'\n", "not a device URL"),
    ],
)
def test_bad_configs_are_clear_errors(text: str, message: str) -> None:
    with pytest.raises(ConfigError, match=message):
        parse_toml(text)


def test_budget_inputs_come_from_scanner_and_motor_errors() -> None:
    cfg = parse_toml(
        REAL + "[scanner.errors]\nrange_offset_u_m = 0.005\nalpha_zero_u_deg = 0.02\n"
        "[motor.errors]\nencoder_u_deg = 0.001\n[fit]\ncoverage_factor = 3\n"
    )
    e = cfg.sensor_errors()
    assert e.range_offset_u_m == 0.005 and e.alpha_zero_u_rad == pytest.approx(np.deg2rad(0.02))
    assert e.encoder_u_rad == pytest.approx(np.deg2rad(0.001)) and cfg.fit.coverage_factor == 3
    d = parse_toml(REAL).sensor_errors()  # defaults: an uncalibrated LMS1xx, +-30 mm rectangular
    assert d.range_offset_u_m == pytest.approx(0.030 / np.sqrt(3)) and d.range_offset_distribution == "rectangular"
    for bad, key in (
        ("[scanner.errors]\nrange_offset_u_m = -0.01", "scanner.errors.range_offset_u_m"),
        ("[motor.errors]\ntiming_jitter_u_s = -1e-3", "motor.errors.timing_jitter_u_s"),
        ("[scanner.errors]\nrange_offset_distribution = 'triangular'", "scanner.errors.range_offset_distribution"),
        ("[fit]\ncoverage_factor = 0", "fit.coverage_factor"),
    ):
        with pytest.raises(ConfigError, match=key.replace(".", r"\.")):
            parse_toml(REAL + bad)


def test_missing_file(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="cannot read config"):
        load_config(tmp_path / "nope.toml")


def test_the_real_rig_example_in_the_docs_is_valid() -> None:
    import re

    from tests.conftest import REPO

    doc = (REPO / "docs" / "service.md").read_text()
    block = re.search(r"A real rig:\n\n```toml\n(.*?)```", doc, re.S)
    assert block is not None
    cfg = parse_toml(block.group(1))
    assert not cfg.is_sim and cfg.motor.url is not None and cfg.motor.url.startswith("canopen+socketcan://")


def test_sim_sensor_model_is_selectable() -> None:
    assert parse_toml("[sim]\n").sim.sensor == "ideal"  # type: ignore[union-attr]
    assert parse_toml("[sim]\nsensor = 'lms1xx'\n").sim.sensor == "lms1xx"  # type: ignore[union-attr]


def test_noise_in_degrees_becomes_the_si_noise_model_once() -> None:
    from lrms.covariance import NoiseModel
    from service.fitting import noise_model

    cfg = parse_toml("[sim]\n[noise]\nsigma_l_m = 0.02\nsigma_alpha_deg = 0.5\nsigma_beta_deg = 0.01\n")
    si = cfg.noise.si()
    assert si == pytest.approx({"sigma_l": 0.02, "sigma_alpha": np.pi / 360, "sigma_beta": np.pi / 18000})
    assert noise_model(cfg) == NoiseModel(**si)


def test_sim_rig_errors_make_the_simulated_rig_differ_from_the_mapping() -> None:
    """[sim] rig_errors: the service maps with [kinematics]; the simulator's true rig adds the errors."""
    from lrms.kinematics import RigCalibration

    cfg = parse_toml(
        "[sim]\nrig_errors = {range_offset_m = 0.02, tilt_x_deg = 0.2, p_m = 0.103}\n[kinematics]\nmotor_zero_deg = 1\n"
    )
    assert cfg.calibration.rig.k0 == 0.0 and cfg.calibration.p == pytest.approx(0.1)
    true = RigCalibration.from_dict(cfg.sim_kinematics)
    assert true.rig.k0 == 0.02 and true.p == 0.103 and true.rig.tilt_x == pytest.approx(np.deg2rad(0.2))
    assert true.motor_zero == pytest.approx(np.deg2rad(1.0))
