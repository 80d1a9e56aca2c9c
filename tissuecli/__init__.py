"""tissuecli: record, identify and render tissue from a sensorised laparoscopic forceps.

The library behind the ``tissuecli`` command. The main names are importable from here
(loaded on first use, so ``import tissuecli`` stays cheap)::

    from tissuecli import fit_session, read_session
    outcome = fit_session(read_session("grasp.h5", "liver-1"))
    print(outcome.bayes.best_.name, outcome.bayes.best_.posterior.mean)

docs/api.md shows recording, fitting and playing from Python; docs/architecture.md
the layers (cli -> app -> report | formats | sim -> hw -> identify | render -> core).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from ._lazy import lazy_getattr
from ._version import __version__

#: public name -> module that defines it
_EXPORTS = {
    # core
    "Session": ".core.session",
    "Tissue": ".core.tissue",
    "Law": ".core.terms",
    "DEFAULT_TISSUE": ".core.tissue",
    "Calibration": ".core.calibration",
    "TissueError": ".core.errors",
    # identify
    "BayesianFit": ".identify.bayes",
    "WindowedPinv": ".identify.pinv",
    "FitOutcome": ".identify.outcome",
    "fit_session": ".identify.outcome",
    # render
    "DisplayProfile": ".render.profile",
    "PAPER_DISPLAY": ".render.profile",
    "check": ".render.check",
    "simulate_offline": ".render.offline",
    # formats
    "read_session": ".formats.sessions",
    "write_session": ".formats.sessions",
    "list_sessions": ".formats.sessions",
    "read_recording": ".formats.recording",
    "read_tissue": ".formats.params",
    "write_params": ".formats.params",
    # hw and sim
    "StopFlag": ".hw.realtime",
    "SimulatorProcess": ".sim.process",
    "ForcepsModel": ".sim.synth",
    "synthesize": ".sim.synth",
    "random_session": ".sim.synth",
    # services
    "record": ".app.record",
    "fit_file": ".app.fit",
    "play": ".app.play",
    "render_report": ".report",
}

__all__ = [
    "__version__",
    "Session",
    "Tissue",
    "Law",
    "DEFAULT_TISSUE",
    "Calibration",
    "TissueError",
    "BayesianFit",
    "WindowedPinv",
    "FitOutcome",
    "fit_session",
    "DisplayProfile",
    "PAPER_DISPLAY",
    "check",
    "simulate_offline",
    "read_session",
    "write_session",
    "list_sessions",
    "read_recording",
    "read_tissue",
    "write_params",
    "StopFlag",
    "SimulatorProcess",
    "ForcepsModel",
    "synthesize",
    "random_session",
    "record",
    "fit_file",
    "play",
    "render_report",
]


__getattr__ = lazy_getattr(__name__, _EXPORTS)


def __dir__() -> list[str]:
    return sorted(__all__)


if TYPE_CHECKING:  # what the lazy names are, for type checkers and editors
    from .app.fit import fit_file
    from .app.play import play
    from .app.record import record
    from .core.calibration import Calibration
    from .core.errors import TissueError
    from .core.session import Session
    from .core.terms import Law
    from .core.tissue import DEFAULT_TISSUE, Tissue
    from .formats.params import read_tissue, write_params
    from .formats.recording import read_recording
    from .formats.sessions import list_sessions, read_session, write_session
    from .hw.realtime import StopFlag
    from .identify.bayes import BayesianFit
    from .identify.outcome import FitOutcome, fit_session
    from .identify.pinv import WindowedPinv
    from .render.check import check
    from .render.offline import simulate_offline
    from .render.profile import PAPER_DISPLAY, DisplayProfile
    from .report import render_report
    from .sim.process import SimulatorProcess
    from .sim.synth import ForcepsModel, random_session, synthesize
