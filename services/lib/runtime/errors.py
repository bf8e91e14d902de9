"""Errors that end a command, and the exit codes they map to (the one home of those codes).

| code | meaning | supervisor |
| --- | --- | --- |
| 0 | done (a finished run, a service stopped by SIGTERM/SIGINT) | - |
| 1 | a failed run, or a bug (an uncaught exception keeps its traceback) | restart |
| 2 | usage error: a bad option, file, parameter or scenario (`UsageError`) | never restart |
| 75 | runtime failure: Zenoh unreachable (`RuntimeFailure`) | restart, with back-off |
| 130 | interrupted (Ctrl-C) | - |

A usage error is the user's to fix: the command line prints one line on stderr and exits 2,
and restarting cannot help. A runtime failure is the environment's (the router is not up yet,
a port is still held by a previous instance): one line on stderr too, and a later attempt may
well succeed, so supervisors restart it.
"""

USAGE_ERROR = 2
# sysexits.h EX_TEMPFAIL: "a temporary failure ... the user is invited to retry later" -- exactly
# an unreachable Zenoh endpoint. It is outside the codes Python (1), argparse (2) and shells
# (126-165, signals) use, so a supervisor can tell it apart from a crash and from a bad setting.
RUNTIME_FAILURE = 75
INTERRUPTED = 130


class UsageError(ValueError):
    """The user's to fix: one line on stderr, exit code USAGE_ERROR, never restarted."""

    exit_code = USAGE_ERROR


class RuntimeFailure(RuntimeError):
    """The environment's (e.g. no Zenoh endpoint answers): one line on stderr, exit code
    RUNTIME_FAILURE, and supervisors restart the process."""

    exit_code = RUNTIME_FAILURE
