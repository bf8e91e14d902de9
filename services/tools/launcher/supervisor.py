"""Starts service processes, prefixes their output, restarts the ones that crash, and
stops all of them (SIGTERM, then SIGKILL after a grace period) leaving nothing behind.

Restarts: a child that exits with a usage error (2) is never restarted; any other exit
(a crash, a signal, RUNTIME_FAILURE = 75 for an unreachable Zenoh) is, the first time at
once and then with back-off (RESTART_BACKOFF_S doubling per restart within the window, at most
RESTART_BACKOFF_MAX_S), so a child that cannot start does not spin; after MAX_RESTARTS
restarts within RESTART_WINDOW_S the child is given up on.

Children are separate processes, never a fork of this one (it holds Zenoh, which is not
fork-safe), each in its own session so a terminal Ctrl-C reaches only the launcher, which then
shuts them down in order.

Warm starts: a service started as `python -m services.tools.launcher.run_service` (or that wrapped into
a network namespace by `ip netns exec`) is forked from the run's fork server
(services/tools/launcher/forkserver.py), an interpreter that loaded the services' libraries once, so
that neither the launch nor a restart pays them again; a fresh interpreter when the server cannot
fork it (gone, or no subreaper here).
"""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from typing import Callable, TextIO

from services.lib.runtime.errors import RUNTIME_FAILURE, USAGE_ERROR
from services.tools.launcher.forkserver import ForkedProcess, ForkServer

MAX_RESTARTS = 5  # within RESTART_WINDOW_S; beyond that the service is given up on
RESTART_WINDOW_S = 60.0
# The first restart within the window is immediate (a killed service is back within 2 s);
# the n-th waits RESTART_BACKOFF_S * 2**(n-2), at most RESTART_BACKOFF_MAX_S: 0, 0.5, 1, 2, 4 s.
RESTART_BACKOFF_S = 0.5
RESTART_BACKOFF_MAX_S = 5.0
SERVICE_MODULE = "services.tools.launcher.run_service"  # a child run as `python -m` this is forked from the fork server


@dataclass
class Child:
    name: str
    argv: list[str]
    process: subprocess.Popen | None = None
    started: float = 0.0
    restarts: list[float] = field(default_factory=list)
    failed: bool = False
    held: bool = False  # killed by a fault and kept down until released
    restart: bool = True  # False: an exit is final (e.g. a viewer that would overwrite its file)
    reader: threading.Thread | None = None
    restart_at: float | None = None  # exited, and to be started again at this time (back-off)
    exit_code: int | None = None  # of the exit that restart_at answers


class Supervisor:
    def __init__(self, out: TextIO = sys.stdout, echo: bool = True,
                 on_restart: Callable[[str, int, float], None] | None = None,
                 log_file: TextIO | None = None) -> None:
        self.children: dict[str, Child] = {}
        self._out = out
        self._echo = echo
        self._lock = threading.Lock()
        self._stopping = False
        self._on_restart = on_restart
        self._log = log_file
        self.width = 10
        self._forkserver: ForkServer | None = None  # started with the first service it can fork
        self.forkserver_cpu_s = 0.0  # the fork server's CPU seconds (the libraries' load), read at its stop

    def start(self, name: str, argv: list[str], restart: bool = True) -> None:
        child = self.children.setdefault(name, Child(name, argv, restart=restart))
        self.width = max(self.width, len(name))
        self._spawn(child)

    def _spawn(self, child: Child) -> None:
        start = _service_start(child.argv)
        forked = self._fork(child.argv, start) if start is not None else None
        child.process = forked or _popen(child.argv, subprocess.DEVNULL)
        child.started = time.monotonic()
        child.restart_at = child.exit_code = None
        child.reader = threading.Thread(target=self._pump_output, args=(child, child.process), daemon=True)
        child.reader.start()

    def _pump_output(self, child: Child, process: subprocess.Popen) -> None:
        for line in process.stdout:
            self.say(line.rstrip("\n"), child.name)
        process.stdout.close()

    def say(self, text: str, source: str = "launcher") -> None:
        line = f"[{source:>{self.width}}] {text}"
        with self._lock:
            if self._log:
                self._log.write(line + "\n")
            if self._echo or source == "launcher":
                print(line, file=self._out, flush=True)

    def poll(self) -> None:
        """Restart children that exited while the run is still going (call it often: a restart
        that waits out its back-off happens in a later call)."""
        if self._stopping:
            return
        for child in self.children.values():
            if child.failed or child.held or child.process is None or child.process.poll() is None:
                continue
            now = time.monotonic()
            if child.restart_at is None:
                self._exited(child, child.process.returncode, now)
            if child.restart_at is not None and now >= child.restart_at:
                code = child.exit_code
                child.restarts.append(now)
                self._spawn(child)
                self.say(f"restarted {child.name} after it exited ({describe_exit(code)})")
                if self._on_restart:
                    self._on_restart(child.name, code, now)

    def _fork(self, argv: list[str], start: ServiceStart) -> ForkedProcess | None:
        """The service forked from the run's fork server (started with the first one), or None."""
        if self._forkserver is None:
            self._forkserver = ForkServer(self._start_forkserver, self.say)
        if not self._forkserver.available:
            return None
        process = self._forkserver.start(start.args, " ".join(argv), start.namespace)
        if process is None:
            self.say("the fork server could not start a service (its output is above); services start "
                     "as fresh interpreters from now on")
        return process

    def _start_forkserver(self, argv: list[str], pass_fds: tuple[int, ...]) -> subprocess.Popen:
        process = _popen(argv, subprocess.DEVNULL, pass_fds)
        threading.Thread(target=self._pump_output, args=(Child("forkserver", argv), process), daemon=True).start()
        return process

    @property
    def forkserver_pid(self) -> int | None:
        server = self._forkserver
        return server.process.pid if server is not None and server.process is not None else None

    def _exited(self, child: Child, code: int, now: float) -> None:
        """Decide what a child's exit means: given up on, or to be restarted (at once or later)."""
        if code == USAGE_ERROR:  # a bad option or parameter: restarting cannot help
            child.failed = True
            self.say(f"{child.name} exited with a usage error (exit code {USAGE_ERROR}); not restarting it")
            return
        if not child.restart:
            child.failed = code != 0
            child.process = None
            self.say(f"{child.name} exited ({describe_exit(code)}); the run goes on without it"
                     + (" and will end with exit code 1" if child.failed else ""))
            return
        child.restarts = [t for t in child.restarts if now - t < RESTART_WINDOW_S]
        if len(child.restarts) >= MAX_RESTARTS:
            child.failed = True
            self.say(f"{child.name} exited ({describe_exit(code)}) {MAX_RESTARTS} times within "
                     f"{RESTART_WINDOW_S:.0f} s; giving up on it")
            return
        delay = restart_delay(len(child.restarts))
        child.exit_code, child.restart_at = code, now + delay
        if delay > 0:
            self.say(f"{child.name} exited ({describe_exit(code)}); restarting it in {delay:g} s "
                     f"(restart {len(child.restarts) + 1} within {RESTART_WINDOW_S:.0f} s)")

    def send(self, name: str, sig: int) -> None:
        child = self.children[name]
        if child.process is not None and child.process.poll() is None:
            _signal_group(child.process, sig)

    def kill(self, name: str, hold: bool = False) -> None:
        """SIGKILL a child (a fault); with hold, it is not restarted until release()."""
        self.children[name].held = hold
        self.send(name, signal.SIGKILL)

    def release(self, name: str) -> None:
        child = self.children[name]
        if child.held:
            child.held = False
            if child.process is not None and child.process.poll() is not None and not self._stopping:
                self._spawn(child)
                self.say(f"started {child.name} again after its fault ended")

    def pid(self, name: str) -> int | None:
        child = self.children.get(name)
        return child.process.pid if child and child.process else None

    def stop_all(self, grace: float = 2.0, last: dict[str, float] | None = None,
                 first: dict[str, float] | None = None, after_first: Callable[[], None] | None = None) -> list[str]:
        """SIGTERM everyone, SIGKILL what is still there after `grace` s; returns the killed ones.
        The children named in `first` are stopped before all others, each with its own grace, and
        `after_first` runs once they are gone (the simulator, whose end the services should see);
        those named in `last` after all others (a viewer that still has to write what it received)."""
        self._stopping = True
        first = {name: g for name, g in (first or {}).items() if name in self.children}
        last = {name: g for name, g in (last or {}).items() if name in self.children and name not in first}
        killed = []
        for name, early_grace in first.items():
            killed += self._stop([self.children[name]], early_grace)
        if first and after_first is not None:
            after_first()
        killed += self._stop([c for c in self.children.values() if c.name not in last and c.name not in first], grace)
        for name, late_grace in last.items():
            killed += self._stop([self.children[name]], late_grace)
        self._stop_forkserver()
        for child in self.children.values():
            if child.reader:
                child.reader.join(timeout=1.0)
        self._log = None  # the caller owns the file
        return killed

    def _stop_forkserver(self) -> None:
        """End the fork server (it exits when its channel closes), killed if it lingers."""
        server = self._forkserver
        if server is None or server.process is None:
            return
        if server.process.poll() is None:  # reaped, its pid may be another process's
            self.forkserver_cpu_s = process_cpu_seconds(server.process.pid)
        server.close()
        try:
            server.process.wait(timeout=2.0)
        except subprocess.TimeoutExpired:
            _signal_group(server.process, signal.SIGKILL)
            server.process.wait()

    def _stop(self, children: list[Child], grace: float) -> list[str]:
        running = [c for c in children if c.process and c.process.poll() is None]
        for child in running:
            _signal_group(child.process, signal.SIGTERM)
        deadline = time.monotonic() + grace
        for child in running:
            try:
                child.process.wait(timeout=max(0.0, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                pass
        killed = []
        for child in children:
            if child.process and child.process.poll() is None:
                killed.append(child.name)
                _signal_group(child.process, signal.SIGKILL)
                child.process.wait()
            elif child.process:
                _signal_group(child.process, signal.SIGKILL)  # grandchildren of a child, if any
        return killed


def _popen(argv: list[str], stdin, pass_fds: tuple[int, ...] = ()) -> subprocess.Popen:
    return subprocess.Popen(
        argv, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, stdin=stdin, start_new_session=True,
        env=dict(os.environ, PYTHONUNBUFFERED="1"), text=True, bufsize=1, errors="replace", pass_fds=pass_fds,
    )


@dataclass(frozen=True)
class ServiceStart:
    """A child the fork server can start: run_service's arguments, in a network namespace or not."""
    args: list[str]
    namespace: str | None = None


def _service_start(argv: list[str]) -> ServiceStart | None:
    """How to fork a child started as `python -m services.tools.launcher.run_service ...` by this
    interpreter, directly or as `ip netns exec NAMESPACE python -m ...`; None for any other."""
    namespace = None
    if len(argv) >= 4 and argv[:3] == ["ip", "netns", "exec"]:
        namespace, argv = argv[3], argv[4:]
    if len(argv) >= 3 and argv[0] == sys.executable and argv[1:3] == ["-m", SERVICE_MODULE]:
        return ServiceStart(argv[3:], namespace)
    return None


def _signal_group(process: subprocess.Popen, sig: int) -> None:
    try:
        os.killpg(process.pid, sig)
    except (ProcessLookupError, PermissionError):
        pass


def process_cpu_seconds(pid: int) -> float:
    """User and system CPU seconds of a running process (/proc/PID/stat); 0 if it is gone."""
    try:
        fields = open(f"/proc/{pid}/stat").read().rsplit(")", 1)[1].split()
    except OSError:
        return 0.0
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def restart_delay(recent_restarts: int) -> float:
    """Back-off before the next restart, given the restarts already made within the window."""
    if recent_restarts == 0:
        return 0.0
    return min(RESTART_BACKOFF_S * 2 ** (recent_restarts - 1), RESTART_BACKOFF_MAX_S)


def describe_exit(code: int) -> str:
    if code < 0:
        try:
            return signal.Signals(-code).name
        except ValueError:
            return f"signal {-code}"
    if code == RUNTIME_FAILURE:
        return f"exit code {code}, a runtime failure such as Zenoh unreachable"
    return f"exit code {code}"
