"""Rendering a tissue on the solenoid haptic display: pure numerics, no port, no file.

- :mod:`~tissuecli.render.profile`: the display's constants (:class:`DisplayProfile`);
- :mod:`~tissuecli.render.plant`: the piston's physics and the one integrator;
- :mod:`~tissuecli.render.law`: the control law (paper eq. 9 for any forms);
- :mod:`~tissuecli.render.controller`: the per-frame host controller;
- :mod:`~tissuecli.render.gains`: gain design and the sampled loop's stability;
- :mod:`~tissuecli.render.check`: the renderability verdict;
- :mod:`~tissuecli.render.offline`: the closed loop without a port;
- :mod:`~tissuecli.render.handover`: a tissue as plain data, for a loop in another process.
"""

from .check import GRASP_FORCE_N, CheckResult, check, working_depth
from .controller import Controller, Step, tracking_bound
from .gains import choose_gains, design_gains
from .law import Gains, RenderLaw, control_voltage
from .offline import simulate_offline
from .plant import piston_step
from .profile import PAPER_DISPLAY, DisplayProfile, profile_from_dict

__all__ = [
    "GRASP_FORCE_N",
    "PAPER_DISPLAY",
    "CheckResult",
    "Controller",
    "DisplayProfile",
    "Gains",
    "RenderLaw",
    "Step",
    "check",
    "choose_gains",
    "control_voltage",
    "design_gains",
    "piston_step",
    "profile_from_dict",
    "simulate_offline",
    "tracking_bound",
    "working_depth",
]
