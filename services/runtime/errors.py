"""Errors that are the user's to fix (a bad option, file, parameter or scenario). The
command line turns them into one line on stderr and exit code 2; anything else is a bug
and keeps its traceback."""


class UsageError(ValueError):
    pass
