"""``lrms fit``: the command line end to end on ray-cast sweeps written to files."""

from __future__ import annotations

import importlib.util
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from bench import seed003_reproduction as seed
from service.cli.main import main
from service.pointio import write_xyz
from tests.conftest import REPO
from tests.fitprobe import fit_probe


@pytest.fixture(scope="module")
def sweep_file(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, float]:
    pts, truth, _ = seed.lrms_sweep(np.random.default_rng(21), clutter=0.1)
    f = tmp_path_factory.mktemp("cli") / "sweep.xyz"
    write_xyz(f, pts)
    return f, truth.diameter


def test_fit_cylinder_json_and_plot(
    sweep_file: tuple[Path, float], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    f, d_true = sweep_file
    png = tmp_path / "fit.png"
    assert main(["fit", str(f), "--model", "cylinder", "--json", "--plot", str(png), "--monte-carlo", "60"]) == 0
    out = json.loads(capsys.readouterr().out)
    for key in ("diameter_m", "axis_point_m", "axis_direction", "rmse_m", "n_inliers", "uncertainty"):
        assert key in out
    u = out["uncertainty"]
    for key in ("k", "d_min_m", "d_max_m", "std_m"):
        assert key in u
    assert abs(out["diameter_m"] - d_true) < 4 * u["std_m"] + 2e-4
    assert u["d_min_m"] < out["diameter_m"] < u["d_max_m"]
    assert u["monte_carlo"]["low_m"] < out["diameter_m"] < u["monte_carlo"]["high_m"]
    assert out["line_of_sight"] is True and abs(out["axis_direction"][2]) > 0.9998
    assert 0 < out["bias_correction_m"] < u["std_m"]  # the silhouette's upward bias, subtracted
    assert np.asarray(out["covariance"]["matrix"]).shape == (5, 5)
    # the GUM budget: rows in quadrature, U = 2 u_c, the fit's own row is the GUM u
    rows = u["budget"]
    assert u["k"] == 2.0 and rows[0]["source"] == "fit (type A)" and rows[0]["u_m"] == u["std_m"]
    assert u["combined_m"] == pytest.approx(float(np.sqrt(sum(r["u_m"] ** 2 for r in rows))), rel=1e-12)
    assert u["expanded_m"] == pytest.approx(2 * u["combined_m"], rel=1e-12)
    assert {r["source"] for r in rows} >= {"range offset", "range scale", "alpha zero", "motor timing jitter"}
    assert abs(out["diameter_m"] - d_true) <= u["expanded_m"]
    # the Monte Carlo replicas draw the same systematic effects: an interval as wide as +-U, roughly
    mc = u["monte_carlo"]
    assert mc["systematics"] is True and mc["multistart"] is True
    assert 0.6 < (mc["high_m"] - mc["low_m"]) / (2 * u["expanded_m"]) < 1.4
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 20_000


def test_fit_without_line_of_sight_is_the_biased_orthogonal_fit(
    sweep_file: tuple[Path, float], capsys: pytest.CaptureFixture[str]
) -> None:
    f, d_true = sweep_file
    assert main(["fit", str(f), "--json", "--no-line-of-sight", "--k", "2"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["line_of_sight"] is False and out["uncertainty"]["critical_point"]["k"] == 2
    # a cloud from elsewhere: no beams, so only the fit's own row and the (absent) edge model
    assert [r["source"] for r in out["uncertainty"]["budget"]] == [
        "fit (type A)",
        "footprint / edge model",
        "edge family (model choice)",
        "footprint bias correction",
    ]
    assert out["bias_correction_m"] is None  # defined for the line-of-sight fit only
    # on this rig's one-sided view the orthogonal fit comes out several mm small
    assert -0.012 < out["diameter_m"] - d_true < -0.004


def test_text_output_through_the_installed_command(sweep_file: tuple[Path, float]) -> None:
    f, _ = sweep_file
    proc = subprocess.run(
        [sys.executable, "-m", "service.cli.main", "fit", str(f), "--sigma-l-mm", "11.67"],
        capture_output=True,
        text=True,
        cwd=REPO,
        timeout=120,
    )
    assert proc.returncode == 0, proc.stderr
    assert "diameter:" in proc.stdout and "critical point (k=3)" in proc.stdout and "GUM" in proc.stdout
    assert "uncertainty budget (GUM):" in proc.stdout and "range offset" in proc.stdout
    assert "expanded U = 2 u_c" in proc.stdout


def test_budget_inputs_from_a_rig_config(
    sweep_file: tuple[Path, float], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    f, _ = sweep_file
    cfg = tmp_path / "rig.toml"
    cfg.write_text(
        "[sim]\n[scanner.errors]\nrange_offset_u_m = 0.002\n[motor.errors]\ntiming_jitter_u_s = 0.0\n"
        "[fit]\ncoverage_factor = 3.0\n"
    )
    assert main(["fit", str(f), "--json", "--config", str(cfg)]) == 0
    u = json.loads(capsys.readouterr().out)["uncertainty"]
    rows = {r["source"]: r for r in u["budget"]}
    assert rows["range offset"]["u_x"] == 0.002 and rows["motor timing jitter"]["u_m"] == 0.0
    assert u["k"] == 3.0 and u["expanded_m"] == pytest.approx(3 * u["combined_m"])
    # a negative uncertainty in the config is a clear one-line error
    cfg.write_text("[sim]\n[scanner.errors]\nrange_offset_u_m = -0.01\n")
    assert main(["fit", str(f), "--config", str(cfg)]) == 1
    err = capsys.readouterr().err
    assert (
        err.startswith("error: ") and "scanner.errors.range_offset_u_m" in err and "greater than or equal to 0" in err
    )


def test_errors_are_one_line_and_exit_1(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    few = tmp_path / "few.xyz"
    write_xyz(few, np.random.default_rng(0).normal(size=(5, 3)))
    assert main(["fit", str(few)]) == 1
    assert capsys.readouterr().err.startswith("error: too few points")
    assert main(["fit", str(tmp_path / "nope.ply")]) == 1
    assert "no such file" in capsys.readouterr().err
    rng = np.random.default_rng(1)
    wall = np.column_stack([rng.uniform(-1, 1, 3000), 3.0 + rng.normal(0, 0.002, 3000), rng.uniform(-1, 1, 3000)])
    write_xyz(tmp_path / "wall.xyz", wall)
    assert main(["fit", str(tmp_path / "wall.xyz")]) == 1
    assert "no cylinder" in capsys.readouterr().err.lower()
    assert main(["fit", str(few), "--sigma-l-mm", "-1"]) == 1
    assert "--sigma-l-mm" in capsys.readouterr().err


def test_elbow_options_and_a_clear_error_without_the_elbow_module(
    sweep_file: tuple[Path, float], monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    from service.cli.main import build_parser

    args = build_parser().parse_args(
        ["fit", "x.xyz", "--model", "elbow", "--degree", "45", "--ratio", "1.5", "--flange"]
    )
    assert (args.model, args.degree, args.ratio, args.flange) == ("elbow", "45", "1.5", True)
    from service.cli import fit
    from service.errors import ServiceError

    f, _ = sweep_file
    args = build_parser().parse_args(["fit", str(f), "--model", "elbow"])
    monkeypatch.setitem(sys.modules, "service.cli.fit_elbow", None)  # as if the elbow module were absent
    with pytest.raises(ServiceError, match="elbow model is not available"):
        fit.run(args)


def test_elbow_is_delegated_to_the_elbow_fit(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from sim.scene.joints import make_joint

    joint = make_joint("a", noise=0.0005, rng=np.random.default_rng(0))
    f = tmp_path / "elbow.xyz"
    write_xyz(f, joint.points)
    assert main(["fit", str(f), "--model", "elbow", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["model"] == "elbow" and out["file"] == str(f)
    assert len(out["center_m"]) == 3


@pytest.mark.parametrize("mode", [[], ["--no-line-of-sight"]], ids=["line-of-sight", "orthogonal"])
def test_fit_of_a_file_leaves_scipy_unimported(tmp_path: Path, mode: list[str]) -> None:
    """The default cylinder fit of a file (thin beam: our own Levenberg-Marquardt, nearest
    neighbours on grids; the normals by an exact k-d tree, since grid normals failed grossly on
    calibrated rig sweeps) runs without :mod:`scipy.optimize` (the footprint fit imports it on
    first use), :mod:`scipy.ndimage` or :mod:`scipy.stats`, each a tenth of a second or more of the command's start
    (bench/bench_cli_start.py), and, with pykdtree installed (the normals' k-d tree then), without
    :mod:`scipy.spatial` (0.3 s). A probe process runs the command itself and lists what it
    loaded; ``--optics lms1xx`` does load scipy.optimize."""
    rng = np.random.default_rng(3)
    t = rng.uniform(-1.0, 1.0, 600)
    pts = np.column_stack([2.5 - 0.138 * np.cos(t), 0.138 * np.sin(t), rng.uniform(-0.2, 0.2, 600)])
    cloud = tmp_path / "c.xyz"
    write_xyz(cloud, pts + rng.normal(0.0, 3e-4, pts.shape))

    heavy = ("scipy.optimize", "scipy.stats", "scipy.ndimage", "matplotlib", "fastapi", "sqlalchemy", "pydantic")
    if importlib.util.find_spec("pykdtree") is not None:  # cKDTree is the normals' fallback without it
        heavy += ("scipy.spatial",)

    def probe(extra: list[str]) -> list[str]:
        status, loaded = fit_probe(cloud, extra, heavy, 2)
        assert status == "0 0.28", status
        return loaded

    assert probe(mode) == []
    if not mode:  # the guard can fail: the footprint-aware fit does need scipy.optimize
        assert "scipy.optimize" in probe(["--optics", "lms1xx"])
