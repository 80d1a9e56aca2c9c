"""Progress of long work, reported by the library and drawn by whoever called it.

Library code never prints: a service or an estimator takes a :class:`Progress` and
tells it where it is (a stage begins, a count advances, a chain grows); the command
line passes one that draws a status line on a terminal, a notebook or a test can pass
its own, and the default does nothing.
"""

from __future__ import annotations


class Progress:
    """Receives the stages of one long job; every method does nothing here.

    A stage runs from its :meth:`stage` call to the next one or to :meth:`close`.
    """

    def stage(self, name: str, total: int | None = None) -> None:
        """A stage begins: ``name`` in a few words (``reading lab.h5``, ``structure
        search``), ``total`` the items it will count if known."""

    def advance(self, done: int, total: int | None = None, note: str = "") -> None:
        """``done`` items of the current stage are finished, of ``total`` if known
        (it may grow: a greedy search learns its length as it goes); ``note`` names
        the item just done."""

    def sampling(self, form: str, steps: int, need: int) -> None:
        """A Markov chain of law ``form`` has ``steps`` steps of about ``need``."""

    def close(self) -> None:
        """The job ended (done or failed)."""

    def __call__(self, form: str, steps: int, tau: float) -> None:
        """The sampler's callback, ``progress(form, steps, tau)``: a chain needs 50
        autocorrelation times and at least 1000 steps."""
        self.sampling(form, steps, max(1000, int(50 * tau)))


#: the progress of work nobody watches
SILENT = Progress()


def as_progress(progress: object) -> Progress:
    """A :class:`Progress` for what a caller passed: itself, :data:`SILENT` for None,
    or a bare ``progress(form, steps, tau)`` callable (sampling alone) wrapped."""
    if progress is None:
        return SILENT
    if isinstance(progress, Progress):
        return progress
    if callable(progress):
        return _Sampling(progress)
    raise TypeError(f"progress must be a Progress or a callable, not {type(progress).__name__}")


class _Sampling(Progress):
    def __init__(self, callback: object) -> None:
        self.callback = callback

    def __call__(self, form: str, steps: int, tau: float) -> None:
        self.callback(form, steps, tau)  # type: ignore[operator]
