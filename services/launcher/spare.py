"""`python -m services.launcher.spare -- ENDPOINTS`: a service process started ahead of need.

The supervisor keeps spare interpreters beside a run (supervisor.py). A spare loads what the
services load before they can serve — numpy, msgspec, Zenoh, the runtime, numba with its compiler
started, and the slow libraries some import right after their token (filterpy with scipy.stats,
scipy.ndimage; services/runtime/warmup.py) — then says so on stdout (READY_LINE) and waits. On a
2-core KVM guest a service takes 1.3-1.7 s from exec to its liveliness token, numba's start-up
alone about 1 s (`import numba` 0.4 s, its first compiled call 0.7 s: the CPU target's registries,
and the scipy.linalg that its BLAS check imports), and up to 0.7 s more before it answers.

When a service exits and is to be restarted, the supervisor writes that service's arguments to a
ready spare's stdin (one JSON list), and the spare becomes the service: it imports the service's
own modules and starts it as `falconry run` would, warm-up, token and first message in the usual
order. A restart then costs the service's own start-up only (0.2-0.7 s there).

The arguments after `--` are the Zenoh endpoints of the run's services, unused: the spare's
command line names the run's endpoint like every other process of the run, so that whatever looks
for the run's processes by their command line finds it too. A service restarted in a spare keeps
the spare's command line; the launcher's log names its pid ("restarted X in a spare, pid N").

Started like every child (exec, never a fork: Zenoh is not fork-safe); it opens no Zenoh session
before it is a service. An empty stdin (the run ended) ends it with 0.
"""
from __future__ import annotations

import json
import sys

READY_LINE = "falconry spare: libraries loaded"  # on stdout, once: the supervisor hands over only then


def load_libraries() -> None:
    import cv2  # noqa: F401  (camera, object_detect)
    import filterpy.kalman  # noqa: F401  (job_manager, tracker; with scipy.stats, which the classifier needs too)
    import numba
    import scipy.ndimage  # noqa: F401  (planner)

    import services.launcher.run_service  # noqa: F401  (numpy, msgspec, Zenoh, the schemas, argparse)
    import services.runtime.node  # noqa: F401

    numba.njit(lambda x: x + 1)(1)  # numba's compiler started: its registries and LLVM loaded


def main() -> int:
    load_libraries()
    print(READY_LINE, flush=True)
    line = sys.stdin.readline()
    if not line.strip():
        return 0
    argv = json.loads(line)
    if not isinstance(argv, list) or not all(isinstance(a, str) for a in argv):
        print("spare: the service's arguments must be one JSON list of strings", file=sys.stderr)
        return 2
    from services.launcher.run_service import main as run_service

    return run_service(argv)


if __name__ == "__main__":
    sys.exit(main())
