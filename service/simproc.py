"""The simulated rig in a child process (``python -m sim.rig``), as :class:`service.rig.Rig` opens
it for a ``[sim]`` config with ``process = true``.

A module of its own (the standard library only) so that the rig process starts the simulated
rig before it imports anything else: :class:`service.supervisor.RigSupervisor` passes
:func:`sim_args` on the rig process's command line, and the rig process
(:func:`service.rigproc.main`) starts the simulated rig from them before it reads its boot
message (which loads the config models) and the rig code, so they all boot at the same time.
"""

from __future__ import annotations

import contextlib
import json
import subprocess
import sys
from typing import TYPE_CHECKING, Any

from service.errors import ServiceError

if TYPE_CHECKING:
    from service.config import RigConfig


def sim_args(config: RigConfig) -> list[str]:
    """The command line of ``python -m sim.rig`` (after ``-m sim.rig``) for a ``[sim]`` config."""
    sim = config.sim
    assert sim is not None
    return [
        "--scene",
        sim.scene,
        "--sensor",
        sim.sensor,
        "--seed",
        str(sim.seed),
        "--cola",
        sim.cola,
        "--can",
        sim.can,
        "--node",
        str(sim.node),
        "--kinematics",
        json.dumps(config.sim_kinematics),
        "--noise",
        json.dumps(config.noise.si()),
    ]


class SimProcess:
    """The simulated rig in a child process (``python -m sim.rig``), served on 127.0.0.1: of a
    ``[sim]`` config, or of its :func:`sim_args` (``args``, without a config)."""

    def __init__(self, config: RigConfig | None = None, wait: bool = True, *, args: list[str] | None = None) -> None:
        if args is None:
            if config is None:
                raise TypeError("SimProcess needs a config or its sim_args")
            args = sim_args(config)
        cmd = [sys.executable, "-m", "sim.rig", *args]
        self.proc = subprocess.Popen(cmd, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
        self.info: dict[str, Any] = {}
        self.scanner_url = ""
        self.motor_url = ""
        if wait:
            self.wait_ready()

    def wait_ready(self) -> None:
        """Wait for the simulated rig's first line (its URLs); a no-op once it came."""
        if self.info:
            return
        assert self.proc.stdout is not None
        line = self.proc.stdout.readline()
        if not line:
            self.proc.wait(10)
            raise ServiceError(f"the simulated rig did not start (exit status {self.proc.returncode})")
        self.info = json.loads(line)
        self.scanner_url = self.info["scanner_url"]
        self.motor_url = self.info["motor_url"]

    def describe(self) -> dict[str, Any]:
        return {**self.info, "pid": self.proc.pid, "alive": self.proc.poll() is None}

    def close(self) -> None:
        if self.proc.poll() is None:
            with contextlib.suppress(OSError):
                assert self.proc.stdin is not None
                self.proc.stdin.close()
            try:
                self.proc.wait(15)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(5)
