"""A passivity observer and controller at the solenoid's port, after Hannaford and Ryu
(2002, "Time-domain passivity control of haptic interfaces").

The port. The piston (mass, spring, damping: passive on its own) meets the solenoid,
which the host drives. Positions and forces are positive down; the solenoid's pull
``u = alpha V^2 >= 0`` acts up, against a closing piston. The power flowing *into* the
host side (solenoid, controller and rendered tissue together) is ``u v``, ``v`` the
piston's velocity: a closing piston (``v > 0``) does work on a pulling solenoid. The
host side is passive, so the whole display is to the hand, when the energy it has
taken in never goes negative::

    E(t_k) = sum_j u_j (x_{j+1} - x_j) >= 0

with ``u_j`` the pull held over ``[t_j, t_{j+1}]`` (the display holds each voltage
for a period, so this sum is the exact work for the encoder's readings, not a
rectangle-rule estimate). A rendered spring stiffer than the piston's takes in
``(K - Kp) x^2 / 2`` and gives it back; a controller that creates energy (the loop's
delay, a law with a negative coefficient, a stiffness raised while the tissue is
compressed) drives ``E`` below zero. ``E`` is the negative of a play's
``actuator_work_j``.

The controller. When ``E``, with the energy the pull already applied will take in
over the current period, is predicted negative, the pull asked for is changed by a
variable damping ``beta v`` chosen so that over the period the new voltage acts
(from the next tick on) it takes in exactly the deficit: ``beta v^2 T = -E``, with
``beta`` capped (a damper acting a period late on the piston's mass must stay well
below ``Mp / T``) and no action below a speed the encoder cannot tell from rest. The
solenoid only pulls, up to ``alpha v_max^2``: closing, the damping pulls harder (up
to saturation); opening, it pulls less (down to 0 V, never a push). What the limits
leave is dissipated in later periods. Nothing changes while ``E >= 0``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

from .profile import DisplayProfile

#: Below this piston speed the controller does not act, m/s: the encoder's 1 um steps
#: make the estimated speed jitter by about 1 mm/s at rest, and a damping sized by a
#: speed that small and of random sign pulls at random, putting energy in, not out.
MIN_SPEED_M_S = 2e-3

#: The added damping ``beta`` is capped at this fraction of ``Mp / T``: a damper
#: acting a period late on a mass turns oscillatory near ``Mp / T`` and unstable at
#: about twice that; at a quarter it stays well damped.
MAX_DAMPING_FRACTION = 0.25


@dataclass(frozen=True)
class PassivityStep:
    """One frame of the passivity controller (SI)."""

    volts: float  # the voltage to send, V, in [0, v_max]
    energy_j: float  # energy the host side has taken in so far, J
    added_pull_n: float  # the damping's change of the pull, N (> 0: pulls harder)


class PassivityController:
    """Observe the energy at the solenoid's port and dissipate any excess the host's
    controller created (see the module's docstring for the port and the signs).

    Call :meth:`update` once per Encoder frame, after the rendering controller, with
    the voltage it asks for.

    Parameters
    ----------
    profile : DisplayProfile
        The display (``alpha``, ``v_max``).
    rate_hz : float
        Loop rate, Hz (for the damping's cap).
    tolerance_j : float
        Energy deficit tolerated before acting, J (0: act on any).
    min_speed : float
        Piston speed below which it does not act, m/s (:data:`MIN_SPEED_M_S`).
    max_damping_fraction : float
        Cap of the added damping as a fraction of ``Mp rate_hz``
        (:data:`MAX_DAMPING_FRACTION`).

    Attributes
    ----------
    energy_j : float
        Observed energy taken in by the host side, J.
    dissipated_j : float
        Energy the added damping took in, J (what the controller dissipated).
    min_energy_j : float
        Lowest observed energy, J.
    acting_frames : int
        Frames on which the controller changed the voltage.
    frames : int
        Frames observed.
    """

    def __init__(
        self,
        profile: DisplayProfile,
        rate_hz: float = 1000.0,
        tolerance_j: float = 0.0,
        min_speed: float = MIN_SPEED_M_S,
        max_damping_fraction: float = MAX_DAMPING_FRACTION,
    ) -> None:
        self.alpha, self.v_max = profile.alpha, profile.v_max
        self.min_speed = min_speed
        self.max_damping = max_damping_fraction * profile.Mp * rate_hz
        self.max_pull = profile.alpha * profile.v_max**2
        self.tolerance_j = tolerance_j
        self.reset()

    def reset(self) -> None:
        """Start observing afresh (at rest: nothing taken in)."""
        self.energy_j = self.dissipated_j = self.min_energy_j = 0.0
        self.acting_frames = self.frames = 0
        self.x_prev = math.nan
        self.pull_prev = 0.0  # pull held over the current period, N
        self.added_applied = 0.0  # damping within it, N
        self.sent_volts = math.nan
        self.added_sent = 0.0  # damping within the voltage sent last, N
        self.damping = 0.0  # the damping last added, N s/m

    def observe(self, position: float, volts_applied: float) -> float:
        """Fold in one reading: ``position`` (m) at this tick and the voltage the
        display applies from it on (V); the observed energy, J."""
        if not (math.isfinite(position) and math.isfinite(volts_applied)):
            return self.energy_j
        if self.x_prev == self.x_prev:
            dx = position - self.x_prev
            self.energy_j += self.pull_prev * dx
            self.dissipated_j += self.added_applied * dx
            self.min_energy_j = min(self.min_energy_j, self.energy_j)
        self.x_prev = position
        self.pull_prev = self.alpha * volts_applied * volts_applied
        # the damping counts as applied only if the display applies what was sent
        same = abs(volts_applied - self.sent_volts) <= 1e-6 * self.v_max
        self.added_applied = self.added_sent if same else 0.0
        self.frames += 1
        return self.energy_j

    def act(self, volts: float, velocity: float, dt: float) -> PassivityStep:
        """The voltage to send instead of ``volts`` (V), given the piston's ``velocity``
        (m/s) expected over the next period and the period ``dt`` (s).

        The voltage acts from the next tick, a period after the one held now, so the
        deficit is predicted at the start of that period: the observed energy plus
        what the pull held now takes in meanwhile (``u v T``).
        """
        volts = min(max(volts, 0.0), self.v_max) if volts == volts else 0.0
        pull = self.alpha * volts * volts
        added = 0.0
        if math.isfinite(velocity) and dt > 0:
            expected = self.energy_j + self.pull_prev * velocity * dt
            if expected < -self.tolerance_j and abs(velocity) > self.min_speed:
                beta = min(-expected / (velocity * velocity * dt), self.max_damping)
                target = min(max(pull + beta * velocity, 0.0), self.max_pull)
                added = target - pull
                if added != 0.0:
                    pull = target
                    volts = min(math.sqrt(pull / self.alpha), self.v_max)
                    self.acting_frames += 1
                    self.damping = beta
        if added == 0.0:
            self.damping = 0.0
        self.sent_volts, self.added_sent = volts, added
        return PassivityStep(volts, self.energy_j, added)

    def update(
        self, position: float, volts_applied: float, volts: float, velocity: float, dt: float
    ) -> PassivityStep:
        """:meth:`observe` then :meth:`act`: one frame."""
        self.observe(position, volts_applied)
        return self.act(volts, velocity, dt)

    def summary(self) -> dict[str, Any]:
        """The figures as a JSON-ready dict, J and frames."""
        return {
            "energy_observed_j": self.energy_j,
            "energy_min_j": self.min_energy_j,
            "energy_dissipated_j": self.dissipated_j,
            "acting_frames": self.acting_frames,
            "acting_fraction": self.acting_frames / max(self.frames, 1),
        }
