"""The fork server (services/tools/launcher/forkserver.py) on its own: real forks of run_service, adopted
and reaped by this process. The supervisor's use of it: tests/test_zenoh_retry.py."""
from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import threading

import pytest

from services.lib.runtime import shm
from services.tools.launcher.forkserver import ForkedProcess, ForkServer
from services.tools.launcher.supervisor import _popen


@pytest.fixture
def server():
    said: list[str] = []
    forks = ForkServer(lambda argv, pass_fds: _popen(argv, subprocess.DEVNULL, pass_fds), said.append)
    assert forks.available, "no child subreaper here"
    output: list[str] = []  # read as it comes, as the launcher does: a full pipe would block the server
    reader = threading.Thread(target=lambda: output.extend(forks.process.stdout), daemon=True)
    reader.start()
    yield forks
    forks.close()
    forks.process.wait(timeout=30)
    reader.join(timeout=10)
    forks.process.stdout.close()


def test_forks_in_a_row_each_run_and_report_their_own_exit_status_and_output(server):
    for _ in range(3):
        fork = server.start(["run", "planner", "--help"], "falconry-test run planner --help")
        assert isinstance(fork, ForkedProcess)
        assert fork.wait(timeout=60) == 0
        assert "usage:" in fork.stdout.read()
        fork.stdout.close()
    fork = server.start(["run", "planner", "--no-such-option"], "falconry-test bad option")
    assert fork.wait(timeout=60) == 2  # argparse's usage error, as an exec'd run_service would give
    assert "--no-such-option" in fork.stdout.read()
    fork.stdout.close()


def test_a_fork_takes_its_command_line_as_its_title(server):
    """Read from a fork that lives on: a service waiting for a Zenoh that is not there."""
    segments = shm.segments()
    title = f"{sys.executable} -m services.tools.launcher.run_service run planner --uav uav9 --connect tcp/127.0.0.1:1"
    waiting = server.start(["run", "planner", "--uav", "uav9", "--connect", "tcp/127.0.0.1:1"], title)
    assert waiting is not None
    try:
        assert os.getsid(waiting.pid) == waiting.pid  # its own session as soon as its pid is known
        waiting.stdout.readline()  # its first line: it runs, and waits for Zenoh
        cmdline = open(f"/proc/{waiting.pid}/cmdline", "rb").read()
        assert b"run planner --uav uav9 --connect tcp/127.0.0.1:1" in cmdline, cmdline
    finally:
        os.kill(waiting.pid, signal.SIGTERM)  # ends the wait for Zenoh: a stop, exit status 0
        assert waiting.wait(timeout=30) == 0
        waiting.stdout.close()
        shm.remove_orphans(shm.segments() - segments)  # its Zenoh's, as the launcher does


def test_a_request_from_other_than_the_servers_parent_is_refused(server, monkeypatch):
    """A request that outlived the launcher that sent it (another process's pid) forks nothing."""
    first = server.start(["run", "planner", "--help"], "t")  # ready, and forking
    assert first.wait(timeout=60) == 0
    first.stdout.close()
    monkeypatch.setattr(os, "getpid", lambda: 1)
    assert server.start(["run", "planner", "--help"], "t") is None
    assert not server.available
    assert server.process.wait(timeout=30) == -signal.SIGKILL  # ended for good


def test_a_fork_without_the_launchers_go_exits_without_running_its_service(server):
    """The launcher gave up on a request after the server forked it (a timeout, an interrupt): it
    closes the go pipe unwritten, and the fork, adopted all the same, exits 0 having run nothing."""
    first = server.start(["run", "planner", "--help"], "t")  # ready, and forking
    assert first.wait(timeout=60) == 0
    first.stdout.close()
    out_read, out_write = os.pipe()
    go_read, go_write = os.pipe()
    request = {"argv": ["run", "planner", "--help"], "title": "t", "netns": None, "launcher": os.getpid()}
    socket.send_fds(server._channel, [json.dumps(request).encode()], [out_write, go_read])
    os.close(out_write)
    os.close(go_read)
    reply = json.loads(server._channel.recv(65536))
    os.close(go_write)  # no go
    fork = ForkedProcess(reply["pid"], open(out_read), ["t"])
    assert fork.wait(timeout=60) == 0
    assert "usage:" not in fork.stdout.read()  # --help never ran
    fork.stdout.close()


def test_a_server_gone_is_no_server_any_more(server):
    server.process.kill()
    server.process.wait(timeout=30)
    assert server.start(["run", "planner", "--help"], "t") is None
    assert not server.available
