"""The project's foundation: device URLs, the command line, and code quality gates."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from drivers import url as durl
from drivers.errors import DeviceURLError
from tests.conftest import REPO
from tests.fitprobe import fit_probe


def test_url_parses_host_port_and_options() -> None:
    u = durl.DeviceURL.parse("tcp://10.0.0.5:2112?cola=b&timeout=0.5")
    assert (u.scheme, u.host, u.port) == ("tcp", "10.0.0.5", 2112)
    assert u.get_str("cola", choices=("a", "b")) == "b"
    assert u.get_float("timeout", 1.0) == 0.5
    u.check_all_used()


def test_url_path_and_family_scheme() -> None:
    u = durl.DeviceURL.parse("modbus-rtu:///dev/ttyUSB0?baud=115200&unit=1")
    assert u.path == "/dev/ttyUSB0" and u.host is None
    assert u.get_int("baud") == 115200 and u.get_int("unit", lo=1, hi=247) == 1
    c = durl.DeviceURL.parse("canopen+socketcand://127.0.0.1:29536/can0?node=1")
    assert c.scheme == "canopen+socketcand" and c.port == 29536 and c.path == "/can0"


@pytest.mark.parametrize(
    "bad",
    ["10.0.0.5:2112", "tcp://host:notaport", "tcp://h:1?cola=a&cola=b"],
)
def test_url_rejects_malformed(bad: str) -> None:
    with pytest.raises(DeviceURLError):
        durl.DeviceURL.parse(bad)


def test_url_rejects_unknown_and_bad_options() -> None:
    u = durl.DeviceURL.parse("tcp://h:1?cloa=b")
    u.get_str("cola", "a")
    with pytest.raises(DeviceURLError, match="cloa"):
        u.check_all_used()
    with pytest.raises(DeviceURLError, match="one of"):
        durl.DeviceURL.parse("tcp://h:1?cola=c").get_str("cola", choices=("a", "b"))
    with pytest.raises(DeviceURLError, match="outside"):
        durl.DeviceURL.parse("x://h?node=200").get_int("node", lo=1, hi=127)


def test_registry_resolves_family_and_lazy_handlers() -> None:
    seen: list[str] = []
    durl.register("testkind", "fam+", lambda u: seen.append(u.scheme) or "opened")
    durl.register("testkind", "lazy", "drivers.url:registered_schemes")
    assert durl.open_device("testkind", "fam+virtual://x") == "opened"
    assert seen == ["fam+virtual"]
    with pytest.raises(DeviceURLError, match="no testkind driver"):
        durl.open_device("testkind", "nope://x")


def test_cli_help_lists_commands() -> None:
    out = subprocess.run(
        [sys.executable, "-m", "service.cli.main", "--help"], capture_output=True, text=True, cwd=REPO, check=True
    ).stdout
    assert "Laser radar measurement system" in out
    from service.cli.main import COMMANDS

    for words in COMMANDS:  # every command module imports and is listed
        assert f"\n    {words[0]} " in out, words
    sim_out = subprocess.run(
        [sys.executable, "-m", "service.cli.main", "sim", "--help"],
        capture_output=True,
        text=True,
        cwd=REPO,
        check=True,
    ).stdout
    assert "scanner" in sim_out and "motor" in sim_out


def test_cli_start_imports_no_numerics_or_simulator() -> None:
    """``lrms`` parses its arguments without importing numpy, the simulator or the web stack: the
    command modules import those inside ``run`` and the sim:// URLs are registered by dotted path
    (each heavy import costs a command-line start tenths of a second)."""
    probe = (
        "import sys\n"
        "from service.cli import main\n"
        "try:\n"
        "    main.main(['--help'])\n"
        "except SystemExit:\n"
        "    pass\n"
        "heavy = ('numpy', 'scipy', 'can', 'sim', 'fastapi', 'matplotlib', 'service.simdevices')\n"
        "print('HEAVY:', ' '.join(m for m in heavy if m in sys.modules))\n"
    )
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, cwd=REPO, check=True)
    assert "Laser radar measurement system" in out.stdout
    assert out.stdout.rstrip().endswith("HEAVY:"), out.stdout[-300:]


def test_fit_of_a_file_imports_no_web_stack_config_or_plots(tmp_path: Path) -> None:
    """``lrms fit FILE`` reads and fits a cloud without pydantic, the rig config, the sweep/MCAP
    log, the web stack or matplotlib (bench/bench_cli_start.py: each costs the start tenths of a
    second); the probe runs the command itself on a small cylinder."""
    import numpy as np

    rng = np.random.default_rng(0)
    t = rng.uniform(-1.0, 1.0, 400)
    pts = np.column_stack([2.5 - 0.138 * np.cos(t), 0.138 * np.sin(t), rng.uniform(-0.2, 0.2, 400)])
    cloud = tmp_path / "c.csv"
    cloud.write_text("x,y,z\n" + "\n".join(f"{a:.6f},{b:.6f},{c:.6f}" for a, b, c in pts))
    heavy = ("pydantic", "service.config", "service.sweep", "mcap", "fastapi", "matplotlib", "sqlalchemy")
    status, loaded = fit_probe(cloud, ["--no-line-of-sight"], heavy, 3)
    assert status == "0 0.276", status
    assert loaded == [], loaded


def test_drivers_and_lrms_never_import_sim_or_service() -> None:
    import re

    pattern = re.compile(r"^\s*(from|import) (sim|service)\b|\"(sim|service)\.[a-z_.]+:", re.M)
    offenders = [
        str(path.relative_to(REPO))
        for pkg in ("drivers", "lrms")
        for path in (REPO / pkg).rglob("*.py")
        if pattern.search(path.read_text())
    ]
    assert offenders == []


def _tool(name: str) -> str:
    exe = shutil.which(name, path=str(REPO / ".venv" / "bin")) or shutil.which(name)
    if exe is None:
        pytest.fail(f"{name} is not installed (it is in the [test] extra)")
    return exe


def test_ruff_clean() -> None:
    proc = subprocess.run([_tool("ruff"), "check", "."], capture_output=True, text=True, cwd=REPO)
    assert proc.returncode == 0, proc.stdout + proc.stderr


def test_mypy_clean() -> None:
    proc = subprocess.run([_tool("mypy")], capture_output=True, text=True, cwd=REPO)
    assert proc.returncode == 0, proc.stdout + proc.stderr
