"""Named exceptions. The CLI turns every :class:`TissueError` into a one-line message and
exits with its :attr:`~TissueError.exit_code` (docs/usage.md, "Exit status")."""

import signal

#: Exit status of a run that ended as asked.
EXIT_OK = 0
#: Exit status of an error a user can fix (bad input, a device that cannot be opened).
EXIT_ERROR = 1
#: Exit status of a run that lost samples or frames (on the line, in the device or in
#: the file it read).
EXIT_LOST_DATA = 3
#: Exit status of a run during which the display's watchdog cut the solenoid.
EXIT_WATCHDOG = 4
#: Exit status of a run whose loop ran off its rate (or missed its periods, or ran them on
#: late answers).
EXIT_OFF_RATE = 5
#: Exit status of a play that did not render the tissue as checked (tracking, saturation).
EXIT_NOT_RENDERED = 6
#: Exit status of a run that lost its device (the forceps or the display went).
EXIT_DEVICE_LOST = 7
#: A run ended by signal ``n`` exits ``128 + n``: 130 Ctrl-C, 129 hang-up, 143 SIGTERM.
EXIT_SIGNAL_BASE = 128


def signal_exit_code(signum: int) -> int:
    """The shell's convention for a command a signal ended: ``128 + signum``."""
    return EXIT_SIGNAL_BASE + int(signum)


def signal_name(signum: int) -> str:
    """``SIGINT (Ctrl-C)``, ``SIGHUP (hang-up)``, ``SIGTERM``: a signal in words."""
    try:
        name = signal.Signals(signum).name
    except ValueError:
        return f"signal {signum}"
    said = {"SIGINT": " (Ctrl-C)", "SIGHUP": " (hang-up)"}
    return name + said.get(name, "")


class TissueError(Exception):
    """Base of every error a user can cause and fix; its message says how."""

    #: the command's exit status when this ends it
    exit_code = EXIT_ERROR


class InputError(TissueError):
    """Bad user input: a file, an option or data that cannot be used."""


class DeviceError(TissueError):
    """A serial device could not be opened, or did not answer as the protocol says."""


class DeviceLost(DeviceError):
    """A device vanished mid-session (unplugged, or its process ended)."""

    exit_code = EXIT_DEVICE_LOST


class StorageError(TissueError):
    """An HDF5 file could not be read or written as asked."""


class SessionExists(StorageError):
    """A session of that name is already in the file; sessions are never overwritten."""


class FitError(TissueError):
    """The data cannot identify the model as asked."""


class RenderError(TissueError):
    """The display cannot render the tissue as asked."""


class RunFault(TissueError):
    """A run went to its end but not as it should have: it lost data, the watchdog cut
    the solenoid, its loop ran off its rate or the tissue was not rendered as checked.
    Raised after everything the run made is written and its summary printed;
    :attr:`exit_code` says which class of fault (the first of :data:`FAULT_ORDER` that
    occurred when several did)."""

    def __init__(self, message: str, exit_code: int = EXIT_ERROR) -> None:
        super().__init__(message)
        self.exit_code = exit_code

    def __reduce__(self) -> tuple[object, ...]:
        return type(self), (str(self), self.exit_code)


#: When a run has several classes of fault, it exits with the first of these it had:
#: a lost device, then the watchdog, the loop off rate, lost data, and a rendering
#: that differs from the check.
FAULT_ORDER = (EXIT_DEVICE_LOST, EXIT_WATCHDOG, EXIT_OFF_RATE, EXIT_LOST_DATA, EXIT_NOT_RENDERED)


def worst_fault(codes: "list[int] | tuple[int, ...] | set[int]") -> int:
    """The exit status of a run with faults of the classes ``codes`` (0 for none)."""
    for code in FAULT_ORDER:
        if code in codes:
            return code
    return max(codes, default=EXIT_OK)


class Interrupted(BaseException):
    """A signal (SIGINT, SIGTERM, SIGHUP) ended a command that had no loop to stop
    cleanly: raised from the signal handler, so that partial outputs are removed on
    the way out; the command exits ``128 + signum``. A ``BaseException``, as
    ``KeyboardInterrupt``, so that no ``except Exception`` swallows it."""

    def __init__(self, signum: int) -> None:
        super().__init__(signum)
        self.signum = int(signum)

    def __str__(self) -> str:
        return f"interrupted by {signal_name(self.signum)}"
