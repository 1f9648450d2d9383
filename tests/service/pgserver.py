"""A throwaway PostgreSQL server for the tests, from Debian's ``postgresql`` package binaries.

``initdb`` into a fresh temporary folder, the server listening on a Unix socket in that folder only
(no TCP port), trust authentication for the one role ``lrms``; stopped and deleted at the end. The
server refuses to run as root: as root, the binaries run as the ``postgres`` user (which the package
creates), else as ``nobody``, through ``runuser``; the folder is then a ``mkdtemp`` folder of its own
(pytest's temporary root is private to root, so that user could not reach a folder inside it).
"""

from __future__ import annotations

import glob
import os
import pwd
import re
import shutil
import subprocess
import tempfile
import uuid
from pathlib import Path

ROLE = "lrms"


def find_bindir() -> Path | None:
    """The newest ``/usr/lib/postgresql/N/bin`` holding ``initdb`` and ``pg_ctl``."""

    def major(p: str) -> int:
        m = re.search(r"/postgresql/(\d+)/", p)
        return int(m.group(1)) if m else 0

    for d in sorted(glob.glob("/usr/lib/postgresql/*/bin"), key=major, reverse=True):
        if (Path(d) / "initdb").is_file() and (Path(d) / "pg_ctl").is_file():
            return Path(d)
    return None


class PostgresServer:
    def __init__(self, bindir: Path, root: Path | None = None) -> None:
        self.bindir = bindir
        self.prefix: list[str] = []
        self.user: str | None = None
        if os.geteuid() == 0:
            self.user = _unprivileged_user()
            self.prefix = ["runuser", "-u", self.user, "--"]
        if root is None or self.user is not None:
            root = Path(tempfile.mkdtemp(prefix="lrms-pg-"))
        self.root = root
        self.data = root / "data"
        if self.user is not None:
            shutil.chown(root, self.user)
        self.started = False

    def _run(self, *args: str) -> None:
        proc = subprocess.run([*self.prefix, *args], capture_output=True, text=True, timeout=120)
        if proc.returncode != 0:
            log = (self.root / "server.log").read_text(errors="replace") if (self.root / "server.log").exists() else ""
            raise RuntimeError(f"{' '.join(args[:2])} failed ({proc.returncode}): {proc.stderr}{proc.stdout}\n{log}")

    def start(self) -> None:
        self._run(str(self.bindir / "initdb"), "-D", str(self.data), "-A", "trust", "-U", ROLE, "-E", "UTF8")
        self._run(
            str(self.bindir / "pg_ctl"),
            "-D",
            str(self.data),
            "-l",
            str(self.root / "server.log"),
            "-w",
            "-t",
            "60",
            "-o",
            f"-k {self.root} -c listen_addresses='' -F",
            "start",
        )
        self.started = True

    def url(self, database: str = "postgres") -> str:
        return f"postgresql://{ROLE}@/{database}?host={self.root}"

    def new_database(self) -> str:
        """The URL of a new, empty database."""
        import psycopg

        name = f"t_{uuid.uuid4().hex[:12]}"
        with psycopg.connect(host=str(self.root), user=ROLE, dbname="postgres", autocommit=True) as conn:
            conn.execute(f'CREATE DATABASE "{name}"')
        return self.url(name)

    def stop(self) -> None:
        try:
            if self.started:
                self._run(str(self.bindir / "pg_ctl"), "-D", str(self.data), "-m", "immediate", "-w", "stop")
                self.started = False
        finally:
            shutil.rmtree(self.root, ignore_errors=True)


def _unprivileged_user() -> str:
    for name in ("postgres", "nobody"):
        try:
            pwd.getpwnam(name)
        except KeyError:
            continue
        return name
    raise RuntimeError("running as root, and neither a 'postgres' nor a 'nobody' user to run PostgreSQL as")
