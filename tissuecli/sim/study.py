"""A simulated tissue study: several tissue groups, several specimens of each that differ
from one another, several sessions (grasps) of each specimen, every session made by the
package's own simulator (:mod:`tissuecli.sim.synth`) with its truth known.

Each coefficient of a specimen is its group's times ``exp(N(0, specimen_sd^2))``, and
each session's is its specimen's times ``exp(N(0, session_sd^2))``: the hierarchical
model of :mod:`tissuecli.identify.hierarchy` on the log scale, so the truth's own
classifier and comparison are known exactly (docs/benchmarks.md).
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, field

import numpy as np

from ..core.session import Session
from ..core.terms import Law
from ..core.tissue import Tissue
from .synth import random_session

PAPER_LAW = Law.of(["x", "xdot", "xddot"])

#: four tissue groups of the paper's linear law, stiffness 250-520 N/m (the jaw-scale
#: range measured on liver is 100-1350 N/m), damping 2-3.5 N s/m, the forceps' mass
GROUPS: dict[str, Tissue] = {
    "fat": Tissue(PAPER_LAW, 250.0, 2.0, 0.05),
    "liver": Tissue(PAPER_LAW, 320.0, 2.5, 0.05),
    "kidney": Tissue(PAPER_LAW, 400.0, 3.0, 0.05),
    "tumour": Tissue(PAPER_LAW, 520.0, 3.5, 0.05),
}


@dataclass(frozen=True)
class StudyDesign:
    """What a simulated study draws.

    Attributes
    ----------
    groups : dict of str to Tissue
        Each group's typical tissue.
    specimens, sessions : int
        Specimens per group, sessions per specimen.
    specimen_sd, session_sd : float
        SD of ln(coefficient) between specimens of a group and between sessions of a
        specimen (0.1 is about 10 %); the mass M is the forceps', shared by all.
    duration_s : float
        Length of each session, s (1 kHz, the default sensors and a random operator).
    operators : int
        Operators taking turns (labels only: each session has its own random motion).
    seed : int
        Seed of everything drawn.
    """

    groups: dict[str, Tissue] = field(default_factory=lambda: dict(GROUPS))
    specimens: int = 10
    sessions: int = 10
    specimen_sd: float = 0.1
    session_sd: float = 0.03
    duration_s: float = 4.0
    operators: int = 2
    seed: int = 0

    @property
    def size(self) -> int:
        """Sessions in the study."""
        return len(self.groups) * self.specimens * self.sessions


@dataclass(frozen=True)
class StudySession:
    """One simulated session with its labels and truth.

    Attributes
    ----------
    session : Session
        Its ``meta`` holds ``tissue``, ``specimen``, ``operator`` and ``note``.
    truth : Tissue
        The tissue this session was simulated from.
    specimen_truth : Tissue
        Its specimen's tissue (before the session-to-session scatter).
    """

    session: Session
    truth: Tissue
    specimen_truth: Tissue


def _scaled(tissue: Tissue, rng: np.random.Generator, sd: float) -> Tissue:
    """``tissue`` with each coefficient but the mass times ``exp(N(0, sd^2))``."""
    factors = np.exp(rng.normal(0.0, sd, tissue.coef.size))
    factors[[t.role == "inertia" for t in tissue.law.terms]] = 1.0
    return Tissue(tissue.law, *(tissue.coef * factors))


def study_sessions(design: StudyDesign) -> Iterator[StudySession]:
    """The study's sessions, group by group, specimen by specimen; named
    ``<group>-<specimen>-<session>`` (e.g. ``liver-03-07``)."""
    rng = np.random.default_rng(design.seed)
    for g, (group, tissue) in enumerate(design.groups.items()):
        for k in range(1, design.specimens + 1):
            specimen = _scaled(tissue, rng, design.specimen_sd)
            for s in range(1, design.sessions + 1):
                truth = _scaled(specimen, rng, design.session_sd)
                seed = int(rng.integers(2**31))
                session, _ = random_session(truth, seed=seed, duration_s=design.duration_s)
                session.name = f"{group}-{k:02d}-{s:02d}"
                session.meta.update(
                    tissue=group,
                    specimen=f"{group}-{k:02d}",
                    operator=f"operator-{(g + k + s) % design.operators + 1}",
                    note=f"simulated study, seed {design.seed}",
                )
                yield StudySession(session, truth, specimen)
