"""The passivity observer and controller, and retargeting without creating energy, on
the offline loop (display physics, one period of delay, controller, finger)."""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np
import pytest

from tissuecli.core.terms import Law
from tissuecli.core.tissue import Tissue
from tissuecli.render import PAPER_DISPLAY, offline
from tissuecli.render.controller import Controller
from tissuecli.render.offline import simulate_offline
from tissuecli.render.passivity import PassivityController
from tissuecli.sim.finger import OperatorForce

LAW = Law.paper("x", "xdot")


def tissue(k: float, s: float = 3.0) -> Tissue:
    return Tissue(LAW, k, s, 0.05)


class ActiveController(Controller):
    """Renders its tissue with 6 N s/m of negative damping: a law that creates energy."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        speed = self.law.speed
        self.law = dataclasses.replace(self.law, speed=lambda v: speed(v) - 6.0 * v)


def test_observer_sees_a_passive_law_as_passive_and_the_controller_never_acts() -> None:
    for k, seed in ((350.0, 1), (600.0, 2), (1200.0, 3)):
        pc = PassivityController(PAPER_DISPLAY)
        run = simulate_offline(tissue(k), OperatorForce(seed=seed), duration_s=4, passivity=pc)
        assert run["energy"].min() >= 0.0
        assert run["energy"][-1] > 0.0  # the tissue's damping took energy in
        assert pc.acting_frames == 0 and pc.dissipated_j == 0.0


def test_the_observed_energy_is_the_solenoids_work_with_the_sign_turned() -> None:
    p = PAPER_DISPLAY
    run = simulate_offline(tissue(600.0), OperatorForce(seed=4), duration_s=3)
    # pull held over each period times the displacement (positive down) over it
    work = -np.sum(p.alpha * run["volts"][:-1] ** 2 * np.diff(run["x"]))
    assert run["energy"][-1] == pytest.approx(-work, rel=1e-3, abs=1e-7)


@pytest.mark.parametrize("seed", [1, 2])
def test_an_active_law_is_caught_and_its_energy_dissipated(
    seed: int, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(offline, "Controller", ActiveController)
    bare = simulate_offline(tissue(600.0), OperatorForce(seed=seed), duration_s=3)
    assert bare["energy"].min() < -5e-3  # the observer sees the creation: mJ, not noise
    pc = PassivityController(PAPER_DISPLAY)
    run = simulate_offline(tissue(600.0), OperatorForce(seed=seed), duration_s=3, passivity=pc)
    assert pc.acting_frames > 0 and pc.dissipated_j > 1e-3
    # what is left is the one period the controller acts late by: under a tenth
    assert run["energy"].min() > 0.1 * bare["energy"].min()
    assert run["energy"].min() > -1.5e-3
    assert np.all((run["volts"] >= 0.0) & (run["volts"] <= PAPER_DISPLAY.v_max))


def test_a_hard_jump_in_stiffness_creates_energy_the_controller_takes_back_part_of(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # the jump as it would be without retarget's guard: the new law at once, mid-press
    monkeypatch.setattr(offline.Controller, "retarget", _hard_switch)
    kw: dict[str, Any] = {"duration_s": 3, "retargets": [(0.5, tissue(1500.0))]}
    bare = simulate_offline(tissue(400.0), OperatorForce(seed=1), **kw)
    assert bare["energy"].min() < -1e-3
    pc = PassivityController(PAPER_DISPLAY)
    run = simulate_offline(tissue(400.0), OperatorForce(seed=1), passivity=pc, **kw)
    assert pc.dissipated_j > 0.0
    assert run["energy"][-1] > 0.5 * bare["energy"][-1]


def _hard_switch(self: Controller, new: Tissue, slew_s: float = 0.0) -> None:
    from tissuecli.render.law import RenderLaw

    self.law = RenderLaw.build(new, self.profile, self.gains)


@pytest.mark.parametrize(("k_old", "k_new"), [(400.0, 1500.0), (1500.0, 400.0), (600.0, 900.0)])
@pytest.mark.parametrize("seed", [1, 2])
def test_retarget_mid_grasp_creates_no_energy(k_old: float, k_new: float, seed: int) -> None:
    pc = PassivityController(PAPER_DISPLAY)
    run = simulate_offline(
        tissue(k_old),
        OperatorForce(seed=seed),
        duration_s=4,
        passivity=pc,
        retargets=[(0.5, tissue(k_new))],  # while the first press rises
    )
    assert run["energy"].min() >= -2e-5  # within RETARGET_ENERGY_J
    assert np.abs(np.diff(run["volts"])).max() < 0.5  # no jolt: under a third of v_max


def test_retarget_reaches_the_new_law() -> None:
    new = tissue(900.0, 5.0)
    ctrl = Controller(tissue(600.0), PAPER_DISPLAY, 1000.0, _gains())
    ctrl.retarget(new, slew_s=0.1)
    for _ in range(99):
        ctrl.update(0.0, 0.0)
    assert ctrl.blend is not None  # still blending after 99 of 100 periods
    half = ctrl.law.static(0.002)
    ctrl.update(0.0, 0.0)
    assert ctrl.blend is None and ctrl.tissue == new
    assert ctrl.law.static(0.002) == pytest.approx(900.0 * 0.002)
    assert half == pytest.approx(0.002 * (600 + 0.99 * 300), rel=1e-9)


def test_a_stiffer_law_waits_while_the_jaws_are_closed() -> None:
    ctrl = Controller(tissue(400.0), PAPER_DISPLAY, 1000.0, _gains())
    ctrl.retarget(tissue(1500.0), slew_s=0.05)
    for _ in range(200):
        ctrl.update(0.003, 0.5)  # held at 3 mm: the new law would store 5 mJ more
    assert ctrl.blend is not None and ctrl.blend.weight[0] == 0.0
    for _ in range(60):
        ctrl.update(0.0, 0.0)  # released
    assert ctrl.blend is None


def _gains() -> Any:
    from tissuecli.render.gains import choose_gains

    return choose_gains(tissue(600.0), PAPER_DISPLAY, 1000.0, 0.005)[0]
