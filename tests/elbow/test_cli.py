"""The elbow commands end to end: ``lrms fit --model elbow``, ``lrms register``, ``lrms brackets``,
run as subprocesses on point files written with :func:`service.pointio.write_xyz`."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from service.pointio import write_xyz
from sim.scene.joints import add_bracket, make_joint, random_pose

REPO = Path(__file__).resolve().parents[2]


def _lrms(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "service.cli.main", *args], capture_output=True, text=True, cwd=REPO, timeout=180
    )


@pytest.fixture(scope="module")
def stations(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path, object, object]:
    rng = np.random.default_rng(12)
    d = tmp_path_factory.mktemp("elbow")
    out = []
    for view in (60.0, 150.0):
        c, rot = random_pose(rng)
        j = make_joint(
            "a", D=0.2, center=c, rot=rot, coverage_deg=180.0, view_deg=view, noise=0.002, step_deg=3.0, rng=rng
        )
        f = d / f"station_{int(view)}.xyz"
        write_xyz(f, j.points)
        out.append((f, j.truth))
    return out[0][0], out[1][0], out[0][1], out[1][1]


def test_fit_elbow_json(stations: tuple[Path, Path, object, object], tmp_path: Path) -> None:
    f, _, truth, _ = stations
    png = tmp_path / "elbow.png"
    proc = _lrms("fit", str(f), "--model", "elbow", "--degree", "90", "--ratio", "free", "--json", "--plot", str(png))
    assert proc.returncode == 0, proc.stderr
    out = json.loads(proc.stdout)
    assert out["model"] == "elbow" and out["converged"] is True
    assert np.linalg.norm(np.array(out["center_m"]) - truth.center) < 0.002  # type: ignore[attr-defined]
    assert abs(abs(float(np.dot(out["axis"], truth.axis))) - 1.0) < 1e-4  # type: ignore[attr-defined]
    assert out["diameter_m"] == pytest.approx(0.2, abs=0.001)
    assert out["bend_radius_m"] == pytest.approx(0.2, abs=0.003)
    assert out["degree"] == 90.0 and out["iterations"] >= 1
    assert out["rmse_m"] == pytest.approx(0.002, rel=0.05)
    for key in ("Xc_m", "Yc_m", "Zc_m", "A_m", "D_m"):
        assert 0 < out["sigma"][key] < 0.001
    for key in ("omega_deg", "psi_deg", "kappa_deg", "axis_deg"):
        assert 0 < out["sigma"][key] < 0.2
    assert {"omega_deg", "psi_deg", "kappa_deg"} <= out.keys()
    assert png.stat().st_size > 10_000


def test_fit_elbow_fixed_ratio_text(stations: tuple[Path, Path, object, object]) -> None:
    f = stations[0]
    proc = _lrms("fit", str(f), "--model", "elbow", "--ratio", "1")
    assert proc.returncode == 0, proc.stderr
    assert "bend_radius_m" in proc.stdout and "diameter_m" in proc.stdout


def test_register_prints_the_transform(stations: tuple[Path, Path, object, object]) -> None:
    a, b, ta, tb = stations
    proc = _lrms("register", str(a), str(b), "--model", "elbow")
    assert proc.returncode == 0, proc.stderr
    mat = np.array([[float(x) for x in line.split()] for line in proc.stdout.strip().splitlines()])
    assert mat.shape == (4, 4)
    r_true = ta.rot.T @ tb.rot  # type: ignore[attr-defined]
    np.testing.assert_allclose(mat[3], [0, 0, 0, 1])
    ang = math.degrees(math.acos(np.clip((np.trace(mat[:3, :3] @ r_true.T) - 1) / 2, -1, 1)))
    assert ang < 0.3
    mapped = mat[:3, :3] @ tb.center + mat[:3, 3]  # type: ignore[attr-defined]
    assert np.linalg.norm(mapped - ta.center) < 0.002  # type: ignore[attr-defined]
    assert "sigma" in proc.stderr
    js = _lrms("register", str(a), str(b), "--json")
    assert js.returncode == 0, js.stderr
    out = json.loads(js.stdout)
    np.testing.assert_allclose(out["transform"]["matrix"], mat, atol=1e-8)


def test_brackets_command(tmp_path: Path) -> None:
    rng = np.random.default_rng(3)
    c, rot = random_pose(rng)
    j = make_joint("a", center=c, rot=rot, coverage_deg=180.0, noise=0.001, step_deg=2.0, rng=rng)
    jb = add_bracket(j, band_width=0.15, rod_length=1.0, spacing=0.02, noise=0.001, rng=rng)
    f = tmp_path / "bracket.xyz"
    write_xyz(f, jb.points)
    proc = _lrms("brackets", str(f), "--json")
    assert proc.returncode == 0, proc.stderr
    out = json.loads(proc.stdout)
    assert out["groups"][0]["n_points"] > 0.5 * np.count_nonzero(jb.portion == 3)
    assert out["cylinder"]["diameter_m"] == pytest.approx(0.03, abs=0.004)
    text = _lrms("brackets", str(f))
    assert text.returncode == 0 and "group 0:" in text.stdout and "bracket (group 0)" in text.stdout


def test_noisy_straight_pipe_exits_1_naming_the_cylinder(tmp_path: Path) -> None:
    """A straight pipe (D = 0.1 m, 0.5 m long, 2,000 points, noise 20 mm) that fit_auto used to
    return as a sharp 45 deg elbow: refused with the straight-cylinder message and status 1."""
    rng = np.random.default_rng(0)
    t = rng.uniform(0, 0.5, 2000)
    ang = rng.uniform(0, 2 * math.pi, 2000)
    pipe = np.column_stack([t, 0.05 * np.cos(ang), 0.05 * np.sin(ang)]) + rng.normal(0, 0.02, (2000, 3))
    f = tmp_path / "noisy_straight.xyz"
    write_xyz(f, pipe)
    proc = _lrms("fit", str(f), "--model", "elbow", "--json")
    assert proc.returncode == 1 and proc.stdout == ""
    assert proc.stderr.startswith("error: no elbow: a straight cylinder fits the points as well")
    assert proc.stderr.count("\n") == 1


def test_errors_exit_1_with_one_line(tmp_path: Path) -> None:
    few = tmp_path / "few.xyz"
    write_xyz(few, np.random.default_rng(0).normal(size=(20, 3)))
    proc = _lrms("fit", str(few), "--model", "elbow")
    assert proc.returncode == 1
    assert proc.stderr.startswith("error: too few points") and proc.stderr.count("\n") == 1
    # a straight pipe is no elbow
    rng = np.random.default_rng(1)
    t = rng.uniform(0, 0.5, 5000)
    ang = rng.uniform(0, math.pi, 5000)
    pipe = np.column_stack([t, 0.05 * np.cos(ang), 0.05 * np.sin(ang)]) + rng.normal(0, 0.0005, (5000, 3))
    straight = tmp_path / "straight.xyz"
    write_xyz(straight, pipe)
    proc = _lrms("fit", str(straight), "--model", "elbow", "--json")
    assert proc.returncode == 1 and proc.stderr.startswith("error: no ") and proc.stdout == ""
    bad = _lrms("fit", str(straight), "--model", "elbow", "--ratio", "0.2")
    assert bad.returncode == 1 and "ratio" in bad.stderr
    clean = tmp_path / "clean.xyz"
    write_xyz(clean, make_joint("b", coverage_deg=180.0, noise=0.001, step_deg=3.0).points)
    nob = _lrms("brackets", str(clean))
    assert nob.returncode == 1 and nob.stderr.startswith("error: no bracket")
