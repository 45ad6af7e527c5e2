"""Error types shared by the core, the drivers and the front ends.

Every message is one sentence a bench operator can act on; the CLI maps the type to the exit status.
"""


class MlaqcError(Exception):
    """Base of all mlaqc errors; `exit_status` is what the CLI returns for it."""

    exit_status = 1


class InputError(MlaqcError, ValueError):
    """Bad user input: a file, option, config or error map that cannot be used (exit status 2)."""

    exit_status = 2


class DeviceError(MlaqcError, RuntimeError):
    """A camera or stage failed, timed out or misbehaved (exit status 3)."""

    exit_status = 3
