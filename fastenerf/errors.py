"""User-facing errors.

Anything a user can cause (a bad file, a bad argument, a missing key) raises a
`FastenerfError` whose message is one line saying what is wrong and where. The CLI
prints that line and exits 2; it never shows a traceback for these.
"""


class FastenerfError(Exception):
    """A problem with the user's input or environment, explained in one line."""


class InputError(FastenerfError, ValueError):
    """Invalid input data: a file, an array, a config value."""


def require(cond: bool, msg: str) -> None:
    """Raise `InputError(msg)` unless `cond`."""
    if not cond:
        raise InputError(msg)
