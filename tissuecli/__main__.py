"""``python -m tissuecli``, and the ``tissuecli`` console script (``run``)."""

import signal
import sys


def run() -> None:
    """Console entry point: load the command line, then run it.

    A Ctrl-C while the command line loads (click and the command modules: tens of
    ms) ends in one line and exit status 130 (128 + SIGINT); nothing has started yet. It is caught
    by a handler that only notes it, because a KeyboardInterrupt raised inside
    Python's import machinery can be swallowed ("Exception ignored in ...
    _get_module_lock"), and the command would then run on as if never stopped.
    """
    interrupted: list[int] = []
    previous = signal.signal(signal.SIGINT, lambda signum, frame: interrupted.append(signum))
    try:
        from .cli import main
    finally:
        signal.signal(signal.SIGINT, previous)
    if interrupted:
        sys.stderr.write("aborted: interrupted by SIGINT (Ctrl-C)\n")
        sys.exit(130)
    main()


if __name__ == "__main__":
    run()
