"""Run ``lrms fit`` in a fresh process and list which heavy modules it loaded (import guards)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

from tests.conftest import REPO


def fit_probe(cloud: Path, args: list[str], heavy: tuple[str, ...], digits: int) -> tuple[str, list[str]]:
    """``lrms fit CLOUD --json *args`` in a new interpreter: its ``"status diameter"`` line (the
    diameter in m rounded to ``digits``) and the modules of ``heavy`` it had imported by the end."""
    code = (
        "import sys, io, contextlib, json\n"
        "from service.cli import main\n"
        "buf = io.StringIO()\n"
        "with contextlib.redirect_stdout(buf):\n"
        f"    status = main.main(['fit', {str(cloud)!r}, '--json', *{args!r}])\n"
        f"print(status, round(json.loads(buf.getvalue())['diameter_m'], {digits}))\n"
        f"print('HEAVY:', *[m for m in {heavy!r} if m in sys.modules])\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=REPO, check=True)
    lines = out.stdout.strip().splitlines()
    return lines[-2], lines[-1].split()[1:]
