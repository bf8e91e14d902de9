"""Helpers for tests that drive whole `falconry sim` runs."""
from __future__ import annotations

import json
import signal
import socket
import subprocess
import time
from pathlib import Path

from services.lib.runtime.zenoh_config import ZenohSettings, open_session


def wait_for_port(port: int, timeout: float = 20.0) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        with socket.socket() as s:
            if s.connect_ex(("127.0.0.1", port)) == 0:
                return
        time.sleep(0.05)
    raise AssertionError(f"nothing listens on {port}")


def join_run(port: int, gossip_connect: bool = True):
    """A session of our own on a running `falconry sim` (like a partner or a ground station).
    gossip_connect=False keeps it on the hub alone, like a ground station behind the radio: no
    direct links to peers in UAV namespaces, whose teardown would leave its close waiting."""
    wait_for_port(port)
    return open_session(ZenohSettings(connect=[f"tcp/127.0.0.1:{port}"], shared_memory=False,
                                      gossip_connect=gossip_connect))


def processes_mentioning(text: str) -> list[int]:
    """The processes whose command line holds `text`, arguments read as separated by spaces: an
    exec'd process separates them by NULs, a service forked from the fork server (its process title)
    by spaces."""
    pids = []
    for cmdline in Path("/proc").glob("[0-9]*/cmdline"):
        try:
            if text.encode() in cmdline.read_bytes().replace(b"\0", b" "):
                pids.append(int(cmdline.parent.name))
        except OSError:
            pass
    return pids


def read_summary(path: Path) -> dict:
    return json.loads(path.read_text())


def end_partner(partner: subprocess.Popen) -> None:
    """Stop a partner process that runs until its stdin closes (thawed first if frozen), and
    reap it; killed if it does not end within 10 s."""
    partner.send_signal(signal.SIGCONT)
    partner.stdin.close()
    try:
        partner.wait(timeout=10)
    except subprocess.TimeoutExpired:
        partner.kill()
        partner.wait()
    partner.stdout.close()


def record_short_run(recording: Path, *sim_args: str) -> None:
    """`falconry sim SIM_ARGS --lockstep --record RECORDING` on a free port, quiet; fails the test
    with the run's output if it fails, and removes the shared-memory segments it left."""
    from services.lib.runtime import shm
    from services.lib.runtime.zenoh_config import free_port
    from tests.conftest import REPO, falconry_argv

    segments_before = shm.segments()
    try:
        run = subprocess.run(
            falconry_argv("sim", *sim_args, "--lockstep", "--quiet", "--progress", "0", "--port", str(free_port()),
                          "--wall-timeout", "60", "--record", str(recording)),
            cwd=REPO, capture_output=True, text=True, timeout=90)
    finally:
        shm.remove_orphans(shm.segments() - segments_before)
    assert run.returncode == 0, run.stdout[-3000:] + run.stderr[-3000:]
