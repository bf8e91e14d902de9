"""The warm start of a run's services: one interpreter loads the libraries, every service is a fork of it.

A run is about 17 processes. A fresh interpreter spends 1.5-3 CPU-s on a 2-core KVM guest before
a service's first message: `import numba` 0.4 s, numba's first compiled call 0.7 s (the CPU target's
registries, and the scipy.linalg its BLAS check imports), filterpy with scipy.stats 1.6 s,
scipy.ndimage, OpenCV, numpy. Started that way, a 2-UAV run spends 46.8 CPU-s on a 2 s mission
(benchmarks/README.md), nearly all of it these imports, and every test that flies a fleet pays it
again. The fork server pays it once per run (`preload`), then forks each service: a service is up
in a fraction of a second, and a crashed one is back as fast.

Why a fork is safe here: the server never opens a Zenoh session (the zenoh module is imported, but
its runtime starts with the first session, in the service), starts no thread of its own, and forks
from its main thread. The threads the libraries start at import (the BLAS thread pools of numpy and
scipy, OpenCV's) are idle pools, none of which a fork inherits; OpenBLAS builds its pool again in
the child (pthread_atfork), as in every numpy program forked by multiprocessing, and the camera and
Object Detect run OpenCV in forks in every run. The launcher itself never forks: it holds Zenoh.

The protocol, over a SOCK_SEQPACKET socket pair:
- server → launcher, once, when the preload is done: JSON {"ready": true};
- launcher → server, per service: JSON {"argv": the service's run_service arguments, "title": its
  command line, "netns": the network namespace to run it in (`ip netns exec`'s NAME) or null,
  "launcher": the launcher's pid} with two file descriptors: the write end of the pipe that
  becomes the service's stdout and stderr, and the read end of the launcher's go;
- server → launcher: JSON {"loading": SERVICE} first if it loads that service's modules and
  kernels for this fork (an optional one's first), then {"pid": N} or {"error": "..."}.
The fork runs the service only once the launcher, holding its pid, writes a byte on the go pipe;
a launcher that gives up on a request (no answer in time, an interrupt) closes it instead, and
kills the server, so that neither a fork in flight nor a request still queued becomes a service
nobody supervises.

The server forks twice: the intermediate child forks the service and exits at once, so the service
is adopted by the launcher, which is a child subreaper (`become_subreaper`); the service tells its
pid once it leads its own session, and the server answers once the intermediate is gone. The
launcher is then the service's parent as with `subprocess`: it reaps it and reads its exit status
(`ForkedProcess`), and the service's `--exit-with-parent` watches the launcher. A service stays a
service if the server dies; the launcher then starts the next ones as fresh interpreters.

Each service gets its own session (setsid, so the launcher's process-group signals reach it and its
children alone), stdin from /dev/null, and its command line as its process title (setproctitle), so
`ps` and /proc/PID/cmdline name it as if it had been exec'd (arguments separated by spaces).
"""
from __future__ import annotations

import atexit
import contextlib
import ctypes
import gc
import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time
import traceback
from typing import IO

MESSAGE_MAX = 65536  # bytes of one request or reply
READY_TIMEOUT_S = 900.0  # the preload: seconds on a warm numba cache, minutes on a cold one and a busy machine
READY_NOTICE_S = 5.0  # a preload longer than this is said in the run's log
REPLY_TIMEOUT_S = 60.0  # a fork takes milliseconds; after this the server is taken for hung
PR_SET_CHILD_SUBREAPER = 36  # linux/prctl.h
CLONE_NEWNET = 0x40000000  # linux/sched.h: setns into a network namespace
NETNS_DIR = "/run/netns"  # where `ip netns add` names its namespaces


def preload(loaded: set[str]) -> None:
    """Import what the services import before they serve, start numba's compiler, and load the
    services every run has (`load`), so that every fork starts with it done."""
    import cv2  # noqa: F401  (camera, object_detect)
    import filterpy.kalman  # noqa: F401  (job_manager; with scipy.stats, which the classifier needs too)
    import numba
    import scipy.ndimage  # noqa: F401  (planner)
    import scipy.stats  # noqa: F401  (classifier)
    import setproctitle  # noqa: F401  (every fork: missing, the server fails and the launcher starts fresh interpreters)

    import services.tools.launcher.run_service  # noqa: F401  (numpy, msgspec, the zenoh module, the schemas)
    from schemas import keys

    numba.njit(lambda x: x + 1)(1)  # numba's compiler started: its registries and LLVM loaded
    for service in (*keys.SIM_SERVICES, *keys.UAV_SERVICES, *keys.CAMERA_SERVICES):
        try:
            load(service, loaded)
        except Exception as error:  # noqa: BLE001  (its forks report it again, as their own start would)
            print(f"forkserver: loading {service} failed: {error}", file=sys.stderr)


def service_name(argv: list[str]) -> str | None:
    """The service run_service's `argv` names, None if it names none (left to the service's own
    start to report)."""
    from schemas import keys

    service = next((argv[i + 1] for i, a in enumerate(argv[:-1]) if a == "run"), None)
    return service if service in keys.SERVICES else None


def load(service: str, loaded: set[str]) -> None:
    """A service's modules imported and its kernels warmed up (Node.preload), unless it is in
    `loaded` already: a kernel compiled here is compiled for every fork, and numba's cache on disk
    is written once, not by each fork at the same time."""
    from services.tools.registry import node_class

    if service not in loaded:
        node_class(service).preload()
        loaded.add(service)


# ---------------------------------------------------------------- the server (its own process)

def serve(channel: socket.socket) -> int:
    loaded: set[str] = set()
    preload(loaded)
    gc.freeze()  # what the preload made stays out of every fork's collections: fewer pages copied
    try:
        channel.send(json.dumps({"ready": True}).encode())
    except (BrokenPipeError, ConnectionError):
        return 0
    while True:
        try:
            message, fds, _, _ = socket.recv_fds(channel, MESSAGE_MAX, 2)
        except ConnectionError:
            return 0
        if not message:  # the launcher closed its end: the run is over
            return 0
        reply = _fork_service(channel, message, fds, loaded)
        for fd in fds:
            os.close(fd)
        try:
            channel.send(json.dumps(reply).encode())
        except (BrokenPipeError, ConnectionError):
            return 0


def _fork_service(channel: socket.socket, message: bytes, fds: list[int], loaded: set[str]) -> dict:
    try:
        request = json.loads(message)
        argv, title, namespace, launcher = request["argv"], request["title"], request["netns"], request["launcher"]
    except (ValueError, KeyError, TypeError) as error:
        return {"error": f"a request that is not {{argv, title, netns, launcher}} JSON: {error}"}
    if launcher != os.getppid():  # the launcher that asked died, and the request outlived it
        return {"error": f"the launcher that asked, pid {launcher}, is not this server's parent"}
    if len(fds) != 2 or not isinstance(argv, list) or not all(isinstance(a, str) for a in argv):
        return {"error": "a request needs two file descriptors and a list of string arguments"}
    if namespace is not None and (not isinstance(namespace, str) or not namespace or "/" in namespace):
        return {"error": f"not a network namespace's name: {namespace!r}"}
    service = service_name(argv)
    if service is not None and service not in loaded:  # an optional one (the oracle, the localizer
        # with GTSAM), loaded once at its first fork for all the UAVs: on a cold numba cache that
        # takes minutes, which the launcher waits out once told
        channel.send(json.dumps({"loading": service}).encode())
        try:
            load(service, loaded)
        except Exception as error:  # noqa: BLE001  (the fork reports it again, as its own start would)
            print(f"forkserver: loading {service} failed: {error}", file=sys.stderr)
    read_pid, write_pid = os.pipe()
    sys.stdout.flush()
    sys.stderr.flush()
    intermediate = os.fork()
    if intermediate == 0:  # the intermediate: forks the service and exits (the service tells its pid)
        try:
            os.close(read_pid)
            forker = os.getpid()
            if os.fork() == 0:
                _become_service(argv, title, namespace, fds, channel, write_pid, forker, launcher)
        finally:
            os._exit(0)
    os.close(write_pid)
    with os.fdopen(read_pid, "rb") as pipe:
        answer = pipe.read()
    os.waitpid(intermediate, 0)
    return {"pid": int(answer)} if answer else {"error": "the service's process could not be forked"}


def _become_service(argv: list[str], title: str, namespace: str | None, fds: list[int],
                    channel: socket.socket, pid_fd: int, intermediate: int, launcher: int) -> None:
    """In the service's process: detach from the server, then run the service; never returns.
    fds: the write end of its stdout pipe and the read end of the launcher's go. Its pid goes to
    `pid_fd` once it leads its own session (so that the launcher's first signal to its process
    group finds it). `intermediate` is the process that forked this one (not os.getppid() here: it
    may have exited before this process first ran), `launcher` the server's parent, which adopts
    this one then. It runs the service only on the launcher's go, a byte the launcher writes once
    it holds the pid: a launcher that gave up on the request (a timeout, an interrupt) or died
    closes the pipe instead, and the fork exits, so that no service runs untracked."""
    code = 1
    out_fd, go_fd = fds
    try:
        channel.close()
        os.setsid()
        null = os.open(os.devnull, os.O_RDONLY)
        os.dup2(null, 0)
        os.close(null)
        os.dup2(out_fd, 1)
        os.dup2(out_fd, 2)
        os.close(out_fd)
        os.write(pid_fd, str(os.getpid()).encode())
        os.close(pid_fd)
        if namespace is not None:
            _enter_network_namespace(namespace)
        signal.signal(signal.SIGINT, signal.default_int_handler)  # an interpreter's own, whatever the server's
        signal.signal(signal.SIGTERM, signal.SIG_DFL)
        import setproctitle  # loaded by the server

        setproctitle.setproctitle(title)
        sys.argv = title.split(" ")
        # until the intermediate has exited and the launcher adopted this process, its parent is
        # not the one --exit-with-parent is to watch
        while os.getppid() == intermediate:
            time.sleep(0.001)
        go = os.read(go_fd, 1)
        os.close(go_fd)
        if not go or os.getppid() != launcher:  # given up on, or the launcher died: nobody supervises it
            code = 0
            return
        from services.tools.launcher.run_service import main

        code = _exit_code(main, argv)
    except BaseException:  # noqa: BLE001  (the service's own errors are handled in _exit_code)
        traceback.print_exc()
    finally:
        with contextlib.suppress(BaseException):
            atexit._run_exitfuncs()  # what a normal interpreter exit runs (logging's flush, ...)
            sys.stdout.flush()
            sys.stderr.flush()
        os._exit(code)


def _enter_network_namespace(name: str) -> None:
    """What `ip netns exec NAME` does for the network: this process (one thread yet, so every thread
    it starts too) joins the namespace. Its mount namespace stays the host's: the services read no
    /sys nor /etc/netns."""
    fd = os.open(os.path.join(NETNS_DIR, name), os.O_RDONLY)
    try:
        if ctypes.CDLL(None, use_errno=True).setns(fd, CLONE_NEWNET) != 0:
            error = ctypes.get_errno()
            raise OSError(error, f"cannot enter network namespace {name}: {os.strerror(error)}")
    finally:
        os.close(fd)


def _exit_code(main, argv: list[str]) -> int:
    """The exit status `python -m services.tools.launcher.run_service ARGV` would have ended with."""
    try:
        result = main(argv)
    except SystemExit as stop:
        result = stop.code
    except KeyboardInterrupt:
        return 128 + signal.SIGINT
    except BaseException:  # noqa: BLE001
        traceback.print_exc()
        return 1
    if result is None:
        return 0
    if isinstance(result, int):
        return result
    print(result, file=sys.stderr)
    return 1


def main() -> int:
    if len(sys.argv) != 2 or not sys.argv[1].isdigit():
        print("usage: python -m services.tools.launcher.forkserver FD (started by the launcher)", file=sys.stderr)
        return 2
    return serve(socket.socket(fileno=int(sys.argv[1])))


# ---------------------------------------------------------------- the launcher's side

def become_subreaper() -> bool:
    """Make this process adopt its descendants that lose their parent (prctl
    PR_SET_CHILD_SUBREAPER), as the fork server's services do; False where it cannot."""
    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        return libc.prctl(PR_SET_CHILD_SUBREAPER, 1, 0, 0, 0) == 0
    except (OSError, AttributeError):
        return False


class ForkedProcess:
    """A service forked by the server and adopted by this process: the part of subprocess.Popen
    the supervisor uses (pid, stdout, poll, wait, returncode)."""

    def __init__(self, pid: int, stdout: IO[str], args: list[str]) -> None:
        self.pid = pid
        self.stdout = stdout
        self.stdin = None
        self.args = args
        self.returncode: int | None = None
        self._lock = threading.Lock()

    def poll(self) -> int | None:
        with self._lock:
            if self.returncode is None:
                try:
                    pid, status = os.waitpid(self.pid, os.WNOHANG)
                except ChildProcessError:  # not ours to reap (no subreaper): gone is all we know
                    self.returncode = 255 if not _alive(self.pid) else None
                else:
                    if pid == self.pid:
                        self.returncode = os.waitstatus_to_exitcode(status)
            return self.returncode

    def wait(self, timeout: float | None = None) -> int:
        deadline = None if timeout is None else time.monotonic() + timeout
        while self.poll() is None:
            if deadline is not None and time.monotonic() >= deadline:
                raise subprocess.TimeoutExpired(self.args, timeout)
            time.sleep(0.005)
        return self.returncode


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


class ForkServer:
    """The launcher's handle on a fork server: `start` forks a service from it; None when the
    server is not there (not started, died, or the platform has no subreaper): start it fresh."""

    def __init__(self, popen, say=lambda text: None) -> None:
        """popen(argv, pass_fds) starts a child the way the supervisor starts any (its output read
        into the run's log); say(text) tells the run's log what the server is doing, when slow."""
        self.process = None
        self._channel: socket.socket | None = None
        self._lock = threading.Lock()
        self._ready = False
        self._say = say
        if not become_subreaper():
            return
        ours, theirs = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
        with theirs:
            self.process = popen([sys.executable, "-m", __name__, str(theirs.fileno())], (theirs.fileno(),))
        self._channel = ours

    @property
    def available(self) -> bool:
        return self._channel is not None

    def start(self, argv: list[str], title: str, namespace: str | None = None) -> ForkedProcess | None:
        """The service `python -m services.tools.launcher.run_service ARGV`, forked (into the network
        namespace `namespace`, if given); None if the server cannot: it is then ended for good, so
        that no request of this launcher can still become a service after it said None. The first
        call waits for the server's preload."""
        with self._lock:
            if self._channel is None or not self._await_ready():
                return None
            out_read, out_write = os.pipe()
            go_read, go_write = os.pipe()
            pid = None
            try:
                request = {"argv": argv, "title": title, "netns": namespace, "launcher": os.getpid()}
                socket.send_fds(self._channel, [json.dumps(request).encode()], [out_write, go_read])
                pid = self._await_pid()
            except (OSError, ValueError):  # it died, or did not answer in time
                pass
            finally:
                os.close(out_write)
                os.close(go_read)
                if pid is None:  # an interrupt included: the fork, if there is one, reads EOF and exits
                    os.close(out_read)
                    os.close(go_write)
                    self._end_locked()
            if pid is None:
                return None
            with contextlib.suppress(OSError):  # a fork that died already: its exit tells the rest
                os.write(go_write, b"1")
            os.close(go_write)
            stdout = open(out_read, "r", buffering=1, errors="replace")  # noqa: SIM115  (the supervisor closes it)
            return ForkedProcess(pid, stdout, [title])

    def _await_pid(self) -> int | None:
        """The server's answer to a request: the fork's pid, or None. A service's first fork may
        load its modules and kernels first (minutes on a cold numba cache): told so, this waits."""
        while True:
            reply = json.loads(self._channel.recv(MESSAGE_MAX) or b"null")
            if isinstance(reply, dict) and "loading" in reply:
                self._channel.settimeout(READY_TIMEOUT_S)
                continue
            self._channel.settimeout(REPLY_TIMEOUT_S)
            pid = reply.get("pid") if isinstance(reply, dict) else None
            return pid if isinstance(pid, int) else None

    def _await_ready(self) -> bool:
        if self._ready:
            return True
        for timeout in (READY_NOTICE_S, READY_TIMEOUT_S):
            self._channel.settimeout(timeout)
            try:
                reply = json.loads(self._channel.recv(MESSAGE_MAX) or b"null")
                self._ready = isinstance(reply, dict) and reply.get("ready") is True
            except TimeoutError:
                if timeout == READY_NOTICE_S:
                    self._say("waiting for the fork server to load the services' libraries "
                              "(on a cold numba cache it compiles their kernels: minutes)")
                    continue
            except (OSError, ValueError):
                pass
            break
        if not self._ready:
            self._end_locked()
            return False
        self._channel.settimeout(REPLY_TIMEOUT_S)
        return True

    def close(self) -> None:
        """Let the server end (it exits when its channel closes)."""
        with self._lock:
            if self._channel is not None:
                self._channel.close()
                self._channel = None

    def _end_locked(self) -> None:
        """The server failed: kill it, so that nothing it still holds is forked, and close its channel."""
        if self.process is not None and self.process.poll() is None:
            with contextlib.suppress(ProcessLookupError, PermissionError):
                os.killpg(self.process.pid, signal.SIGKILL)
        if self._channel is not None:
            self._channel.close()
            self._channel = None


if __name__ == "__main__":
    sys.exit(main())
