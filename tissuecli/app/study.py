"""The ``simulate study`` service: a simulated tissue study written as labelled HDF5
sessions (:mod:`tissuecli.sim.study`), for the docs, the tests and the benchmark."""

from __future__ import annotations

import os
from collections.abc import Callable

from ..core.errors import InputError
from ..formats.outputs import Output, check_outputs
from ..formats.sessions import write_session
from ..sim.study import StudyDesign, study_sessions


def write_study(
    path: str | os.PathLike[str],
    design: StudyDesign,
    *,
    progress: Callable[[int, int], None] | None = None,
) -> int:
    """Simulate ``design`` and write each session to ``path`` (a new HDF5 file), with its
    labels (``tissue``, ``specimen``, ``operator``, ``note``) as session attributes.

    Returns
    -------
    int
        Sessions written.

    Raises
    ------
    InputError
        If ``path`` exists (a study is written whole, never added to a file).
    """
    if os.path.exists(path):
        raise InputError(f"--out {path} exists; a study goes to a new file: choose another path")
    check_outputs([Output(path, "--out")])
    total = design.size
    if total == 0:
        raise InputError("the study is empty: give at least one group, specimen and session")
    for i, drawn in enumerate(study_sessions(design), 1):
        write_session(path, drawn.session)
        if progress is not None:
            progress(i, total)
    return total
