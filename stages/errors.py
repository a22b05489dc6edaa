"""One exception hierarchy for everything the command line reports as a runtime failure.

A :class:`VetError` becomes a one-line ``vet <command>: error: ...`` message and exit
status 1, except a :class:`UsageError`, which the command line reports as click does a
bad argument (exit status 2); anything else is a bug and shows its traceback.
"""

from __future__ import annotations


class VetError(Exception):
    """A runtime failure that is the input's or the environment's fault, not a bug."""


class InputError(VetError):
    """Unreadable, malformed or inconsistent input (files, arguments, specs)."""


class UsageError(InputError):
    """An argument that cannot be used as given, found only once the command knows more
    than its options (the scene's size, whether standard input is a terminal): the
    command line's usage error, exit status 2. ``option`` names the option at fault
    (``"--motion"``), if one is."""

    def __init__(self, message: str, option: str | None = None):
        super().__init__(message)
        self.option = option


class FormatError(InputError):
    """A file that is not a valid vet file of the expected kind."""


class OutputError(VetError):
    """An output that could not be written (full disk, read-only folder, closed pipe)."""


class DeviceError(VetError):
    """A camera or LCoS controller failed, disconnected or broke the protocol."""
