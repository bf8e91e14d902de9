"""A Zenoh endpoint that is down: services wait for it (retrying with back-off) and come up when
it appears; a bad setting is still a usage error (exit 2) at once; the launcher's supervisor
restarts a runtime failure (exit 75) with back-off and never a usage error.

The "router" here is a plain Zenoh peer listening on the test's own loopback port: it routes
between the clients connected to it, as zenohd does."""
from __future__ import annotations

import io
import os
import queue
import signal
import subprocess
import sys
import threading
import time

import pytest

from schemas import keys
from services.lib.runtime import shm
from services.lib.runtime.errors import RUNTIME_FAILURE, USAGE_ERROR
from services.lib.runtime.zenoh_config import ZenohConfigError, ZenohSettings, build, init_logging, open_session
from services.tools.launcher import supervisor as supervision
from services.tools.launcher.forkserver import ForkedProcess
from services.tools.launcher.supervisor import Supervisor, restart_delay
from tests.conftest import REPO, falconry_argv
from tests.tools.health import health, wait_healthy
from tests.tools.run import processes_mentioning

pytestmark = pytest.mark.alone  # waits and reconnections timed on the wall clock

RETRY_LINE = "waiting for zenoh"


class Lines:
    """A process's output lines, read as they come, with the time each arrived."""

    def __init__(self, stream) -> None:
        self.queue: queue.SimpleQueue = queue.SimpleQueue()
        self.seen: list[str] = []
        self._thread = threading.Thread(target=self._read, args=(stream,), daemon=True)
        self._thread.start()

    def _read(self, stream) -> None:
        try:
            for line in stream:
                self.queue.put(line.rstrip("\n"))
        except (OSError, ValueError):  # closed by the fixture's clean-up
            pass

    def wait_for(self, text: str, count: int = 1, timeout: float = 10.0) -> list[str]:
        deadline = time.monotonic() + timeout
        while sum(text in line for line in self.seen) < count:
            try:
                self.seen.append(self.queue.get(timeout=max(0.0, deadline - time.monotonic())))
            except queue.Empty:
                raise AssertionError(f"no {count}x {text!r} within {timeout} s; output so far:\n"
                                     + "\n".join(self.seen)) from None
        return [line for line in self.seen if text in line]


def listening_peer(endpoint: str):
    init_logging()
    return open_session(ZenohSettings(listen=[endpoint], shared_memory=False))


def liveliness_tokens(session, key_expr: str) -> list[str]:
    return [str(r.ok.key_expr) for r in session.liveliness().get(key_expr, timeout=1.0) if r.ok is not None]


def test_run_waits_for_a_router_that_is_down_and_comes_up_when_it_appears(processes, port):
    endpoint = f"tcp/127.0.0.1:{port}"
    started = time.monotonic()
    proc = processes.start("run", "tracker", "--uav", "uav1", "--clock", "wall",
                           "--zenoh-profile", "router", "--connect", endpoint)
    output = Lines(proc.stdout)
    retries = output.wait_for(RETRY_LINE, count=2, timeout=15)
    assert all(endpoint in line and "attempt" in line for line in retries), retries
    assert proc.poll() is None, "the service gave up instead of waiting"
    router = listening_peer(endpoint)
    appeared = time.monotonic()
    try:
        found = wait_healthy(router, [("uav1", "tracker")], timeout=10)
        came_up = time.monotonic() - appeared
        assert found[("uav1", "tracker")].pid == proc.pid
        assert keys.alive("uav1", "tracker") in liveliness_tokens(router, keys.alive("uav1", "*"))
        output.wait_for("after", timeout=5)  # "zenoh session open (...) after N attempts in S s"
        print(f"tracker answered {came_up:.2f} s after the router appeared "
              f"({time.monotonic() - started:.1f} s after its start)")
        assert came_up < 7.0  # the back-off never waits more than 5 s
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=5) == 0
    finally:
        router.close()
    assert "Traceback" not in "\n".join(output.seen)


def test_sigterm_and_ctrl_c_end_the_wait_at_once(processes, port):
    endpoint = f"tcp/127.0.0.1:{port}"
    for sig in (signal.SIGTERM, signal.SIGINT):
        proc = processes.start("run", "planner", "--uav", "uav1", "--zenoh-profile", "router", "--connect", endpoint)
        output = Lines(proc.stdout)
        output.wait_for(RETRY_LINE, count=2, timeout=15)
        asked = time.monotonic()
        proc.send_signal(sig)
        code = proc.wait(timeout=5)
        took = time.monotonic() - asked
        print(f"{signal.Signals(sig).name} during the retries: exit {code} after {took * 1000:.0f} ms")
        assert code == 0 and took < 1.0
        output.wait_for("stopped before zenoh answered", timeout=2)


def test_connect_timeout_exits_with_the_runtime_failure_code_in_one_line(port):
    endpoint = f"tcp/127.0.0.1:{port}"
    started = time.monotonic()
    result = subprocess.run(falconry_argv("run", "tracker", "--uav", "uav1", "--zenoh-profile", "router",
                                          "--connect", endpoint, "--connect-timeout", "1.5"),
                            cwd=REPO, capture_output=True, text=True, timeout=30)
    took = time.monotonic() - started
    assert result.returncode == RUNTIME_FAILURE, result.stderr
    assert "Traceback" not in result.stderr
    errors = [line for line in result.stderr.splitlines() if "error:" in line]
    assert len(errors) == 1 and "cannot open zenoh session" in errors[0] and endpoint in errors[0], result.stderr
    assert sum(RETRY_LINE in line for line in result.stderr.splitlines()) >= 2, result.stderr
    print(f"gave up after {took:.1f} s (1.5 s of retries): {errors[0]}")

    # a one-shot command tries once by default
    result = subprocess.run(falconry_argv("health", "--zenoh-profile", "router", "--connect", endpoint),
                            cwd=REPO, capture_output=True, text=True, timeout=30)
    assert result.returncode == RUNTIME_FAILURE and "Traceback" not in result.stderr, result.stderr


def test_well_formed_endpoints_pass_and_malformed_ones_are_named():
    for endpoint in ("tcp/127.0.0.1:7447", "tcp/[::1]:7447", "tcp/zenoh:7447", "udp/10.0.0.1:7447#iface=eth0",
                     "tls/uav2.radio:7447?prio=1-7", "unixsock-stream//tmp/zenoh.sock"):
        build(ZenohSettings(profile="router", connect=[endpoint]))
    build(ZenohSettings(listen=["tcp/0.0.0.0:0"]))
    for endpoint, why in (("tcp/127.0.0.1", "HOST:PORT"), ("tcp/:7447", "HOST:PORT"), ("tcp/[::1]", "HOST:PORT"),
                          ("tcp/127.0.0.1:0", "from 1 to 65535"), ("tcp/host:http", "HOST:PORT"),
                          ("zenoh:7447", "PROTOCOL/ADDRESS"), ("tpc/127.0.0.1:7447", "unknown protocol 'tpc'")):
        with pytest.raises(ZenohConfigError, match=why):
            build(ZenohSettings(profile="router", connect=[endpoint]))


@pytest.mark.parametrize("args, expected", [
    (("--zenoh-profile", "mesh"), "invalid choice"),
    (("--zenoh-config", "/nonexistent/zenoh.json5"), "zenoh config file not found"),
    (("--connect", "tcp/127.0.0.1"), "give HOST:PORT"),
    (("--connect", "tcpp/127.0.0.1:7447"), "unknown protocol 'tcpp'"),
    (("--connect", "127.0.0.1:7447"), "an endpoint is PROTOCOL/ADDRESS"),
    (("--listen", "tcp/127.0.0.1:99999"), "port from 0 to 65535"),
    (("--connect-timeout", "-1"), "--connect-timeout must be 0 or more"),
])
def test_a_bad_zenoh_setting_is_still_a_usage_error_at_once(args, expected, port):
    # with a router that is down: a bad setting must not be mistaken for it and retried
    argv = ["run", "tracker", "--uav", "uav1", "--zenoh-profile", "router", "--connect", f"tcp/127.0.0.1:{port}"]
    result = subprocess.run(falconry_argv(*argv, *args), cwd=REPO, capture_output=True, text=True, timeout=30)
    assert result.returncode == USAGE_ERROR, result.stderr
    assert "Traceback" not in result.stderr and RETRY_LINE not in result.stderr, result.stderr
    lines = result.stderr.splitlines()
    assert len(lines) == 1 and expected in lines[0], result.stderr


def test_sim_waits_for_its_router_and_a_service_restarted_while_it_is_down_comes_back(processes, port, tmp_path):
    """Under `falconry sim --zenoh-profile router`: the launcher waits for a router that is not up
    yet; later the router goes away, a service is killed and restarted meanwhile (before, its
    restart exited 2 and was never tried again): it waits too, and is back once the router is."""
    endpoint = f"tcp/127.0.0.1:{port}"
    light = tmp_path / "light.toml"
    light.write_text('[sensor_driver]\nmodel = "os0-32-512"\n')
    log = tmp_path / "run.log"
    launcher = processes.start("sim", "mbzirc", "--uavs", "2", "--duration", "120", "--config", str(light),
                               "--detector", "classifier",  # the router's absence is the subject
                               "--quiet", "--progress", "0", "--log-file", str(log),
                               "--zenoh-profile", "router", "--connect", endpoint)
    output = Lines(launcher.stdout)
    output.wait_for(RETRY_LINE, count=2, timeout=15)
    router = listening_peer(endpoint)
    try:
        before = wait_healthy(router, [("sim", "simulator"), ("uav1", "tracker")], timeout=30)
        router.close()
        os.kill(before[("uav1", "tracker")].pid, signal.SIGKILL)
        output.wait_for("restarted uav1/tracker", timeout=5)
        deadline = time.monotonic() + 10
        while "uav1/tracker" not in "".join(line for line in log.read_text().splitlines() if RETRY_LINE in line):
            assert time.monotonic() < deadline, "the restarted tracker did not wait for the router"
            time.sleep(0.1)
        router = listening_peer(endpoint)
        back = time.monotonic()
        after = wait_healthy(router, [("uav1", "tracker"), ("sim", "simulator")], timeout=10)
        print(f"restarted tracker answered {time.monotonic() - back:.2f} s after the router came back")
        assert after[("uav1", "tracker")].pid != before[("uav1", "tracker")].pid
        assert after[("sim", "simulator")].pid == before[("sim", "simulator")].pid
        assert health(router, "uav2", "tracker") is not None  # the others reconnected by themselves
        launcher.send_signal(signal.SIGINT)
        assert launcher.wait(timeout=30) == 130
    finally:
        router.close()
    output.wait_for("Falconry run summary", timeout=5)
    text = "\n".join(output.seen)
    assert "not restarting" not in text and "giving up" not in text, text


# ---------------------------------------------------------------- the supervisor, with tiny children
def fake(code: int, after: float = 0.0) -> list[str]:
    return [sys.executable, "-c", f"import sys, time; time.sleep({after}); sys.exit({code})"]


def run_supervisor(sup: Supervisor, until, timeout: float) -> None:
    deadline = time.monotonic() + timeout
    while not until() and time.monotonic() < deadline:
        sup.poll()
        time.sleep(0.01)


def test_supervisor_restarts_a_runtime_failure_with_back_off_and_never_a_usage_error(monkeypatch):
    monkeypatch.setattr(supervision, "RESTART_BACKOFF_S", 0.2)
    monkeypatch.setattr(supervision, "RESTART_BACKOFF_MAX_S", 0.5)
    assert [restart_delay(n) for n in range(5)] == [0.0, 0.2, 0.4, 0.5, 0.5]
    out = io.StringIO()
    restarts: list[tuple[str, int, float]] = []
    sup = Supervisor(out=out, echo=False, on_restart=lambda name, code, at: restarts.append((name, code, at)))
    sup.start("flaky", fake(RUNTIME_FAILURE))
    sup.start("misconfigured", fake(USAGE_ERROR))
    first_start = sup.children["flaky"].started
    try:
        run_supervisor(sup, lambda: sup.children["flaky"].failed and sup.children["misconfigured"].failed, 15)
    finally:
        sup.stop_all()
    log = out.getvalue()
    flaky, misconfigured = sup.children["flaky"], sup.children["misconfigured"]
    assert misconfigured.failed and not misconfigured.restarts, log
    assert "misconfigured exited with a usage error (exit code 2); not restarting it" in log
    assert flaky.failed and "giving up on it" in log and "exit code 75" in log, log
    assert [(name, code) for name, code, _ in restarts] == [("flaky", RUNTIME_FAILURE)] * supervision.MAX_RESTARTS
    starts = [first_start] + [at for _, _, at in restarts]
    gaps = [b - a for a, b in zip(starts, starts[1:])]
    print("flaky started again after", ", ".join(f"{g:.2f} s" for g in gaps))
    # each child lives a few ms: the first restart is at once, every later one waits out its back-off
    for n, gap in enumerate(gaps):
        assert gap >= restart_delay(n) - 0.01, gaps
    assert gaps[0] < 1.0, gaps


def test_supervisor_brings_back_a_service_that_failed_to_reach_zenoh(tmp_path):
    """Exit 75 twice (the router is not up yet), then it stays up: restarted, not given up on."""
    counter = tmp_path / "attempts"
    script = (f"import pathlib, sys, time; p = pathlib.Path({str(counter)!r}); "
              f"n = int(p.read_text()) + 1 if p.exists() else 1; p.write_text(str(n)); "
              f"sys.exit({RUNTIME_FAILURE}) if n < 3 else time.sleep(30)")
    out = io.StringIO()
    restarted: list[tuple[str, int]] = []
    sup = Supervisor(out=out, echo=False, on_restart=lambda name, code, _t: restarted.append((name, code)))
    sup.start("service", [sys.executable, "-c", script])
    try:
        run_supervisor(sup, lambda: counter.exists() and counter.read_text() == "3", timeout=10)
        time.sleep(0.3)
        sup.poll()
        child = sup.children["service"]
        assert child.process.poll() is None and not child.failed, out.getvalue()
        assert restarted == [("service", RUNTIME_FAILURE)] * 2
        assert "restarting it in 0.5 s" in out.getvalue()  # the second restart waited
    finally:
        sup.stop_all(grace=1.0)


def test_services_are_forks_of_the_fork_server_and_come_back_as_forks_and_the_run_leaves_none(port):
    """A service started as run_service is forked from the run's fork server: adopted by this process
    (the supervisor is its parent, so it reaps it and reads its exit), named by its command line, and
    answering health with its own pid; its exit status is its own. Killed, it comes back as a new
    fork. With the server gone, the next restart is a fresh interpreter. Stopping the supervisor ends
    the service and the server."""
    endpoint = f"tcp/127.0.0.1:{port}"
    segments = shm.segments()
    out, lines = io.StringIO(), io.StringIO()
    sup = Supervisor(out=out, echo=False, log_file=lines)
    sup.start("uav1/job_manager", [sys.executable, "-m", supervision.SERVICE_MODULE, "run", "job_manager",
                                   "--uav", "uav1", "--listen", endpoint])
    child = sup.children["uav1/job_manager"]
    try:
        run_supervisor(sup, lambda: "up (pid" in lines.getvalue(), timeout=60)
        server, first = sup.forkserver_pid, sup.pid("uav1/job_manager")
        assert server is not None and isinstance(child.process, ForkedProcess), out.getvalue()
        assert _parent(first) == os.getpid()
        cmdline = open(f"/proc/{first}/cmdline", "rb").read()
        assert b"run job_manager --uav uav1" in cmdline and f":{port}".encode() in cmdline, cmdline
        os.kill(first, signal.SIGKILL)
        run_supervisor(sup, lambda: lines.getvalue().count("up (pid") == 2, timeout=20)
        second = sup.pid("uav1/job_manager")
        assert second != first and isinstance(child.process, ForkedProcess) and _parent(second) == os.getpid()
        assert "restarted uav1/job_manager after it exited (SIGKILL)" in out.getvalue(), out.getvalue()
        session = open_session(ZenohSettings(connect=[endpoint], shared_memory=False))
        try:
            answer = wait_healthy(session, [("uav1", "job_manager")])[("uav1", "job_manager")]
        finally:
            session.close()
        assert answer.pid == second and answer.state == "running", answer
        # a fork's exit status is its own: a bad option is a usage error, never restarted
        sup.start("uav1/misconfigured", [sys.executable, "-m", supervision.SERVICE_MODULE, "run", "planner",
                                         "--uav", "uav1", "--no-such-option"])
        assert isinstance(sup.children["uav1/misconfigured"].process, ForkedProcess)
        run_supervisor(sup, lambda: sup.children["uav1/misconfigured"].failed, timeout=20)
        assert "uav1/misconfigured exited with a usage error" in out.getvalue(), out.getvalue()
        assert "--no-such-option" in lines.getvalue(), lines.getvalue()  # argparse's line, through the pipe
        os.kill(server, signal.SIGKILL)
        while _state(server) not in ("Z", None):
            time.sleep(0.01)  # dead (not yet reaped): the next restart cannot reach it any more
        os.kill(second, signal.SIGKILL)
        run_supervisor(sup, lambda: lines.getvalue().count("up (pid") == 3, timeout=30)
        assert isinstance(child.process, subprocess.Popen), out.getvalue()
        assert "the fork server could not start a service" in out.getvalue(), out.getvalue()
    finally:
        sup.stop_all(grace=2.0)
        shm.remove_orphans(shm.segments() - segments)  # the killed services', as the launcher does
    time.sleep(0.2)
    assert processes_mentioning(f":{port}") == [], "the service outlived the supervisor"
    assert not os.path.exists(f"/proc/{server}"), "the fork server outlived the supervisor"


def _state(pid: int) -> str | None:
    try:
        return open(f"/proc/{pid}/stat").read().rsplit(")", 1)[1].split()[0]
    except OSError:
        return None


def _parent(pid: int) -> int:
    return int(open(f"/proc/{pid}/stat").read().rsplit(")", 1)[1].split()[1])
