"""The fork server (services/launcher/forkserver.py) on its own: real forks of run_service, adopted
and reaped by this process. The supervisor's use of it: tests/test_zenoh_retry.py."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import pytest

from services.launcher.forkserver import ForkedProcess, ForkServer
from services.launcher.supervisor import _popen
from services.runtime import shm


@pytest.fixture
def server():
    forks = ForkServer(lambda argv, pass_fds: _popen(argv, subprocess.DEVNULL, pass_fds))
    assert forks.available, "no child subreaper here"
    yield forks
    forks.close()
    forks.process.wait(timeout=30)
    forks.process.stdout.close()


def test_forks_in_a_row_each_run_and_exit(server):
    for _ in range(4):
        fork = server.start(["run", "planner", "--help"], "falconry-test run planner --help")
        assert isinstance(fork, ForkedProcess)
        assert fork.wait(timeout=60) == 0
        assert "usage:" in fork.stdout.read()
        fork.stdout.close()


def test_a_fork_reports_its_own_exit_status_and_output(server):
    fork = server.start(["run", "planner", "--no-such-option"], "falconry-test bad option")
    assert fork.wait(timeout=60) == 2  # argparse's usage error, as an exec'd run_service would give
    assert "--no-such-option" in fork.stdout.read()
    fork.stdout.close()
    assert os.path.exists(f"/proc/{os.getpid()}")  # still here: the fork's exit never ends the launcher


def test_a_fork_takes_its_command_line_as_its_title(server):
    """Read from a fork that lives on: a service waiting for a Zenoh that is not there."""
    segments = shm.segments()
    title = f"{sys.executable} -m services.launcher.run_service run planner --uav uav9 --connect tcp/127.0.0.1:1"
    waiting = server.start(["run", "planner", "--uav", "uav9", "--connect", "tcp/127.0.0.1:1"], title)
    try:
        deadline, cmdline = time.monotonic() + 30, b""
        while b"run_service" not in cmdline and time.monotonic() < deadline:
            time.sleep(0.05)
            cmdline = open(f"/proc/{waiting.pid}/cmdline", "rb").read()
        assert b"run planner --uav uav9 --connect tcp/127.0.0.1:1" in cmdline, cmdline
    finally:
        os.kill(waiting.pid, signal.SIGTERM)  # ends the wait for Zenoh: a stop, exit status 0
        assert waiting.wait(timeout=30) == 0
        waiting.stdout.close()
        shm.remove_orphans(shm.segments() - segments)  # its Zenoh's, as the launcher does


def test_a_server_gone_is_no_server_any_more(server):
    server.process.kill()
    server.process.wait(timeout=30)
    assert server.start(["run", "planner", "--help"], "t") is None
    assert not server.available
