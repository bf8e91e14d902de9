"""Shared fixtures: real Zenoh sessions on per-test loopback ports, real service processes,
and a check that every test leaves no processes and no Zenoh shared-memory files behind."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from services.lib.runtime import shm
from services.lib.runtime.zenoh_config import ZenohSettings, free_port, init_logging, open_session

REPO = Path(__file__).resolve().parent.parent

# A suite started in the background by a non-interactive shell (`make test &`, nohup) inherits
# SIGINT ignored, and every process it starts would inherit that too: the tests that stop a
# launcher or a viewer the way Ctrl-C does would wait in vain. Children of a process that handles
# SIGINT get the default action back.
if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
    signal.signal(signal.SIGINT, signal.default_int_handler)


def _children(pid: int) -> list[int]:
    out = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[1]) == pid and fields[0] != "Z" and not _is_multiprocessing_helper(stat.parent):
            out.append(int(stat.parent.name))
    return out


def _is_multiprocessing_helper(proc: Path) -> bool:
    """multiprocessing's spawn start method keeps one resource tracker per interpreter."""
    try:
        return b"resource_tracker" in (proc / "cmdline").read_bytes()
    except OSError:
        return False


@pytest.fixture(scope="session", autouse=True)
def zenoh_runtime_warmed():
    """Zenoh keeps one /dev/shm segment per process until the interpreter exits; create ours
    before any test's baseline so the leak check sees only what tests leave behind."""
    init_logging()
    open_session(ZenohSettings(listen=["tcp/127.0.0.1:0"], shared_memory=False)).close()


@pytest.fixture(autouse=True)
def leaves_nothing_behind(zenoh_runtime_warmed):
    before_shm = shm.segments()
    yield
    deadline = time.monotonic() + 5.0
    while _children(os.getpid()) and time.monotonic() < deadline:
        time.sleep(0.05)
    leftovers = _children(os.getpid())
    for pid in leftovers:
        os.kill(pid, signal.SIGKILL)
    assert not leftovers, f"test left child processes behind: {leftovers}"
    # Segments of ended processes are removed by whoever supervised them (launcher, Processes).
    # A worker of `pytest -n` cannot tell its leaks from the other worker's fleet (a killed UAV's
    # segments stay orphaned until that run ends): the controller checks the whole session instead.
    if not os.environ.get("PYTEST_XDIST_WORKER"):
        orphans = shm.orphans(shm.segments() - before_shm)
        assert not orphans, f"test left /dev/shm files: {orphans}"


@pytest.fixture
def port() -> int:
    return free_port()


@pytest.fixture
def hub(port):
    """A Zenoh peer session listening on this test's own loopback port: (session, endpoint)."""
    init_logging()
    endpoint = f"tcp/127.0.0.1:{port}"
    session = open_session(ZenohSettings(listen=[endpoint], shared_memory=False))
    yield session, endpoint
    session.close()


def falconry_argv(*args: str) -> list[str]:
    return [sys.executable, "-m", "services.tools.launcher", *args]


class Processes:
    """Service processes started for one test; all stopped (and reaped) at teardown."""

    def __init__(self) -> None:
        self.procs: list[subprocess.Popen] = []
        self.segments_before = shm.segments()

    def start(self, *args: str, **kwargs) -> subprocess.Popen:
        kwargs.setdefault("stdout", subprocess.PIPE)
        kwargs.setdefault("stderr", subprocess.STDOUT)
        proc = subprocess.Popen(falconry_argv(*args), cwd=REPO, text=True, **kwargs)
        self.procs.append(proc)
        return proc

    def stop_all(self) -> None:
        for proc in self.procs:
            if proc.poll() is None:
                proc.send_signal(signal.SIGTERM)
        for proc in self.procs:
            try:
                proc.wait(timeout=5)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
            if proc.stdout:
                proc.stdout.close()
        shm.remove_orphans(shm.segments() - self.segments_before)


@pytest.fixture
def processes():
    procs = Processes()
    yield procs
    procs.stop_all()


SEGMENTS_AT_START = pytest.StashKey[set]()
_SPELLS_ALONE: dict[Path, bool] = {}


def pytest_itemcollected(item):
    """`make test`'s second part collects only the tests/test_*.py files that spell `mark.alone`
    (grep): a test marked so another way, or in another file, would silently run in neither part."""
    if item.get_closest_marker("alone") is not None:
        spelled = _SPELLS_ALONE.setdefault(item.path, "mark.alone" in item.path.read_text()
                                           and item.path.parent == Path(__file__).parent
                                           and item.path.match("test_*.py"))
        if not spelled:
            raise pytest.UsageError(f"{item.nodeid} is marked alone, but its file is not a tests/test_*.py that "
                                    "spells `mark.alone`: make test's second part (the files grep finds) would "
                                    "leave it out")


@pytest.hookimpl(trylast=True)  # after `-m` has deselected: only the tests that run count
def pytest_collection_modifyitems(config, items):
    """The files whose tests take longest first (by their `slow` markers), each file's tests in
    their order. `make test`'s two workers take whole files in this order (pytest-xdist,
    `--dist loadfile --no-loadscope-reorder`): a file that flies missions for minutes, started
    last, would leave one worker to finish alone."""
    seconds: dict[Path, float] = {}
    for item in items:
        marker = item.get_closest_marker("slow")
        if marker is not None and len(marker.args) != 1:
            raise pytest.UsageError(f"{item.nodeid}: slow takes the test's seconds, e.g. @pytest.mark.slow(30)")
        seconds[item.path] = seconds.get(item.path, 0.0) + (float(marker.args[0]) if marker else 0.0)
    items.sort(key=lambda item: -seconds[item.path])  # stable: files stay whole


def pytest_sessionstart(session):
    session.config.stash[SEGMENTS_AT_START] = shm.segments()


def pytest_sessionfinish(session):
    """The controller of `pytest -n`, once its workers are gone: no test may have left a Zenoh
    segment behind (each worker skips the per-test check). A worker hands its fuzz counts to the
    controller, which prints the table."""
    workeroutput = getattr(session.config, "workeroutput", None)
    if workeroutput is None and getattr(session.config.option, "numprocesses", None):
        orphans = shm.orphans(shm.segments() - session.config.stash[SEGMENTS_AT_START])
        if orphans:
            session.config.get_terminal_writer().line(f"the tests left /dev/shm files: {sorted(map(str, orphans))}",
                                                      red=True)
            session.exitstatus = pytest.ExitCode.TESTS_FAILED
    fuzz = sys.modules.get("tests.tools.fuzz")
    if workeroutput is not None and fuzz:
        workeroutput["fuzz_cases_run"] = {name: {"services": run.services, "cases": dict(run.cases)}
                                          for name, run in session.config.stash.get(fuzz.CASES_RUN, {}).items()}


@pytest.hookimpl(optionalhook=True)  # a pytest-xdist hook: unknown to a run without it
def pytest_testnodedown(node, error):
    """The controller's side of pytest_sessionfinish: a worker's fuzz counts added to its own."""
    counted = getattr(node, "workeroutput", {}).get("fuzz_cases_run")
    if not counted:
        return
    from tests.tools.fuzz import CASES_RUN, FuzzRun

    runs = node.config.stash.setdefault(CASES_RUN, {})
    for name, run in counted.items():
        merged = runs.setdefault(name, FuzzRun(services=run["services"]))
        merged.cases.update(run["cases"])


def pytest_terminal_summary(terminalreporter, exitstatus, config):
    """The fuzz cases run per message type (tests/test_fuzz_messages.py), once per session."""
    fuzz = sys.modules.get("tests.tools.fuzz")  # imported only by a session that fuzzes (or merged its workers')
    runs = config.stash.get(fuzz.CASES_RUN, {}) if fuzz else {}
    if not runs:
        return
    terminalreporter.section("fuzz cases run per message type")
    terminalreporter.write_line(f"{'message type':<20}" + "".join(f"{f:>9}" for f in fuzz.FAMILIES)
                                + f"{'total':>9}  through")
    for name, run in sorted(runs.items()):
        terminalreporter.write_line(f"{name:<20}" + "".join(f"{run.cases[f]:>9}" for f in fuzz.FAMILIES)
                                    + f"{sum(run.cases.values()):>9}  {', '.join(run.services)}")
