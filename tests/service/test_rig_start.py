"""A rig process that cannot start says why and leaves no simulated rig behind.

The rig process (``python -m service.rigproc``) starts the simulated rig first thing, before it
reads its boot message; whatever stops it then (a boot message it cannot unpickle, as when the
service and the rig process run different code; a start that raises) must close the simulated
rig and reach the service as :class:`service.rigproc.StartupFailed` with the reason, not as a
bare ``exit status 1``. The simulated rig is found by its command line (a seed no other test
uses) while the rig process starts, and checked by its pid afterwards.
"""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest

from service.config import RigConfig, load_config
from service.rigproc import RigProcessError, StartupFailed
from service.simproc import sim_args
from service.supervisor import RigSupervisor
from tests.conftest import REPO


def _config(tmp_path: Path) -> RigConfig:
    """The default simulated rig (``process = true``) with a seed that names its simulated rig."""
    cfg = load_config(storage_dir=tmp_path)
    assert cfg.sim is not None and cfg.sim.process
    seed = 700_000_000 + (os.getpid() * 1000 + time.monotonic_ns() // 1000) % 100_000_000
    return cfg.model_copy(update={"sim": cfg.sim.model_copy(update={"seed": seed})})


def _sim_pids(seed: int) -> set[int]:
    """The pids of running ``python -m sim.rig`` processes started with ``--seed SEED``."""
    found = set()
    for entry in os.scandir("/proc"):
        if not entry.name.isdigit():
            continue
        try:
            argv = Path(entry.path, "cmdline").read_bytes().split(b"\0")
        except OSError:
            continue
        if b"sim.rig" in argv and b"--seed" in argv and str(seed).encode() in argv:
            found.add(int(entry.name))
    return found


def _running(pid: int) -> bool:
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return False
    return stat.rsplit(")", 1)[1].split()[0] != "Z"


@contextmanager
def _watch_sims(seed: int) -> Iterator[set[int]]:
    """Collects the pids of the simulated rig with ``seed`` while the block runs."""
    seen: set[int] = set()
    done = threading.Event()

    def watch() -> None:
        while not done.wait(0.005):
            seen.update(_sim_pids(seed))

    t = threading.Thread(target=watch, daemon=True)
    t.start()
    try:
        yield seen
    finally:
        done.set()
        t.join()


def _assert_sims_gone(seen: set[int], kill: Callable[[int], None] = lambda pid: None) -> None:
    assert seen, "the simulated rig was never seen: the test did not exercise its start"
    left = {pid for pid in seen if _running(pid)}
    for pid in left:  # do not leave it behind even when the test fails
        kill(pid)
    assert not left, f"the simulated rig is still running: pids {sorted(left)}"


def test_a_start_that_raises_is_reported_and_closes_the_simulated_rig(tmp_path: Path) -> None:
    """The rig process's logging set-up rejects the level (an exception in the start before the
    rig opens): the service's error names it, and the simulated rig started before is closed."""
    cfg = _config(tmp_path)
    assert cfg.sim is not None
    sup = RigSupervisor(cfg, log_level="no-such-level", start_timeout_s=60.0)
    with _watch_sims(cfg.sim.seed) as seen, pytest.raises(RigProcessError) as err:
        sup.open()
    msg = str(err.value)
    assert msg.startswith("the rig process did not start: ValueError: Unknown level"), msg
    _assert_sims_gone(seen, lambda pid: os.kill(pid, 9))
    assert sup.pid is None  # nothing was kept as the rig process


def test_a_boot_message_that_does_not_unpickle_is_reported_and_closes_the_simulated_rig(tmp_path: Path) -> None:
    """``python -m service.rigproc FD SIM_ARGS`` as the supervisor starts it, sent a boot message
    naming a module it does not have (a service of another version): ``StartupFailed`` with the
    import error, exit status 1, the simulated rig closed."""
    from multiprocessing.connection import Connection

    cfg = _config(tmp_path)
    assert cfg.sim is not None
    ours, theirs = socket.socketpair()
    argv = [sys.executable, "-m", "service.rigproc", str(theirs.fileno()), json.dumps(sim_args(cfg))]
    with _watch_sims(cfg.sim.seed) as seen:
        proc = subprocess.Popen(argv, pass_fds=[theirs.fileno()], stdin=subprocess.DEVNULL, cwd=REPO)
        theirs.close()
        conn = Connection(ours.detach())
        try:
            # wait until the simulated rig runs, then send a pickle (protocol 0: GLOBAL, STOP) of a
            # class in a module the rig process cannot import
            deadline = time.monotonic() + 30.0
            while not seen and time.monotonic() < deadline:
                time.sleep(0.01)
            conn.send_bytes(b"cservice.no_such_module_of_another_version\nBoot\n.")
            assert conn.poll(60.0), "no answer from the rig process"
            answer = conn.recv()
            code = proc.wait(30.0)
        finally:
            conn.close()
            if proc.poll() is None:
                proc.kill()
                proc.wait(5.0)
    assert isinstance(answer, StartupFailed), answer
    assert answer.reason.startswith("ModuleNotFoundError: No module named 'service.no_such_module"), answer.reason
    assert code == 1
    _assert_sims_gone(seen, lambda pid: os.kill(pid, 9))
