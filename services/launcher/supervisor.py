"""Starts service processes, prefixes their output, restarts the ones that crash, and
stops all of them (SIGTERM, then SIGKILL after a grace period) leaving nothing behind.

Restarts: a child that exits with a usage error (2) is never restarted; any other exit
(a crash, a signal, RUNTIME_FAILURE = 75 for an unreachable Zenoh) is, the first time at
once and then with back-off (RESTART_BACKOFF_S doubling per restart within the window, at most
RESTART_BACKOFF_MAX_S), so a child that cannot start does not spin; after MAX_RESTARTS
restarts within RESTART_WINDOW_S the child is given up on.

Children are separate interpreters started with subprocess (exec, never a bare fork of
this process: Zenoh is not fork-safe), each in its own session so a terminal Ctrl-C
reaches only the launcher, which then shuts them down in order.

Spares: a service started as `python -m services.launcher.run_service` (not one wrapped into a
network namespace) is restarted in one of SPARES interpreters that have loaded the libraries the
services load (services/launcher/spare.py), when one is ready, so that the restart costs the
service's own start-up only; otherwise in a fresh interpreter. Spares are started SPARE_AFTER_S
after the last first start (out of the launch's way), replaced SPARE_AGAIN_S after one is used
(once the restarted service has had the CPU for its start), and given up on after
MAX_SPARE_FAILURES of them exited unused (each failure doubles the wait for the next).
"""
from __future__ import annotations

import contextlib
import json
import os
import signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from typing import Callable, TextIO

from services.launcher.spare import READY_LINE
from services.runtime.errors import RUNTIME_FAILURE, USAGE_ERROR

MAX_RESTARTS = 5  # within RESTART_WINDOW_S; beyond that the service is given up on
RESTART_WINDOW_S = 60.0
# The first restart within the window is immediate (a killed service is back within 2 s);
# the n-th waits RESTART_BACKOFF_S * 2**(n-2), at most RESTART_BACKOFF_MAX_S: 0, 0.5, 1, 2, 4 s.
RESTART_BACKOFF_S = 0.5
RESTART_BACKOFF_MAX_S = 5.0
SERVICE_MODULE = "services.launcher.run_service"  # a child run as `python -m` this can be restarted in a spare
SPARES = 2  # the second covers a crash that follows another while the first one's replacement loads
SPARE_AFTER_S = 5.0  # after the last first start
SPARE_AGAIN_S = 1.0  # after a spare became a service
MAX_SPARE_FAILURES = 3


@dataclass
class Spare:
    process: subprocess.Popen
    ready: threading.Event = field(default_factory=threading.Event)  # it printed READY_LINE


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
        self._spares: list[Spare] = []
        self._spares_due = time.monotonic() + SPARE_AFTER_S
        self._spare_failures = 0

    def start(self, name: str, argv: list[str], restart: bool = True) -> None:
        child = self.children.setdefault(name, Child(name, argv, restart=restart))
        self.width = max(self.width, len(name))
        self._spawn(child)

    def _spawn(self, child: Child) -> None:
        args = _service_args(child.argv)
        spare = self._take_spare() if child.restarts and args is not None else None
        if spare is not None and _hand_over(spare, args):
            child.process = spare
            self._spares_due = time.monotonic() + SPARE_AGAIN_S
            self.say(f"restarting {child.name} in a spare, pid {spare.pid}")
        else:
            child.process = _popen(child.argv, subprocess.DEVNULL)
            if not child.restarts:  # a first start: the launch goes on
                self._spares_due = max(self._spares_due, time.monotonic() + SPARE_AFTER_S)
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
        that waits out its back-off happens in a later call), and keep the spares ready."""
        if self._stopping:
            return
        self._keep_spares()
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

    @property
    def ready_spares(self) -> list[int]:
        """The pids of the spares ready to become a restarted service, oldest first."""
        return [s.process.pid for s in self._spares if s.ready.is_set() and s.process.poll() is None]

    def _take_spare(self) -> subprocess.Popen | None:
        """The oldest ready spare, or None (one still loading would start the service later than a
        fresh interpreter: it loads more than a service needs before its token)."""
        for spare in self._spares:
            if spare.ready.is_set() and spare.process.poll() is None:
                self._spares.remove(spare)
                return spare.process
        return None

    def _keep_spares(self) -> None:
        now = time.monotonic()
        for spare in [s for s in self._spares if s.process.poll() is not None]:
            self._spares.remove(spare)
            self._spare_failures += 1
            self._spares_due = now + SPARE_AFTER_S * 2 ** self._spare_failures
            self.say(f"a spare interpreter exited unused ({describe_exit(spare.process.returncode)})"
                     + ("; no more spares: restarts start fresh interpreters"
                        if self._spare_failures == MAX_SPARE_FAILURES else ""))
        if len(self._spares) >= SPARES or now < self._spares_due or self._spare_failures >= MAX_SPARE_FAILURES:
            return
        endpoints = sorted({a for c in self.children.values() for a in _endpoints(_service_args(c.argv) or [])})
        if any(_service_args(c.argv) is not None for c in self.children.values()):
            spare = Spare(_popen([sys.executable, "-m", "services.launcher.spare", "--", *endpoints], subprocess.PIPE))
            threading.Thread(target=self._await_ready, args=(spare,), daemon=True).start()
            self._spares.append(spare)

    def _await_ready(self, spare: Spare) -> None:
        """Read a spare's output until it is ready (anything else it says goes to the log); after
        that its output is the service's, read by _pump_output."""
        for line in iter(spare.process.stdout.readline, ""):
            if line.rstrip("\n") == READY_LINE:
                spare.ready.set()
                return
            self.say(line.rstrip("\n"), f"spare {spare.process.pid}")

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
        for spare in self._spares:  # first: one still loading would take CPU from the children's stop
            _signal_group(spare.process, signal.SIGKILL)
            spare.process.wait()
            spare.process.stdin.close()
        self._spares = []
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
        for child in self.children.values():
            if child.reader:
                child.reader.join(timeout=1.0)
        self._log = None  # the caller owns the file
        return killed

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


def _popen(argv: list[str], stdin) -> subprocess.Popen:
    return subprocess.Popen(
        argv, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, stdin=stdin, start_new_session=True,
        env=dict(os.environ, PYTHONUNBUFFERED="1"), text=True, bufsize=1, errors="replace",
    )


def _hand_over(spare: subprocess.Popen, args: list[str]) -> bool:
    """Tell a spare which service to become; False if it died meanwhile."""
    try:
        spare.stdin.write(json.dumps(args) + "\n")
        spare.stdin.close()
    except OSError:  # BrokenPipeError: it died since it was ready
        _signal_group(spare, signal.SIGKILL)
        spare.wait()
        for pipe in (spare.stdin, spare.stdout):
            with contextlib.suppress(OSError):
                pipe.close()
        return False
    return True


def _service_args(argv: list[str]) -> list[str] | None:
    """The arguments of a child started as `python -m services.launcher.run_service ...` by this
    interpreter (not wrapped into a network namespace), else None."""
    if len(argv) >= 3 and argv[0] == sys.executable and argv[1:3] == ["-m", SERVICE_MODULE]:
        return argv[3:]
    return None


def _endpoints(args: list[str]) -> list[str]:
    """The Zenoh endpoints a service's arguments name (after --connect or --listen)."""
    return [value for option, value in zip(args, args[1:]) if option in ("--connect", "--listen")]


def _signal_group(process: subprocess.Popen, sig: int) -> None:
    try:
        os.killpg(process.pid, sig)
    except (ProcessLookupError, PermissionError):
        pass


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
