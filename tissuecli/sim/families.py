"""Laws of each family beyond the paper's four forms, with coefficients a simulated
forceps session identifies: what the family benchmark and the tests simulate."""

from __future__ import annotations

from ..core.terms import Law
from ..core.tissue import Tissue

#: one tissue per family (SI coefficients in the law's order)
FAMILIES: dict[str, Tissue] = {
    "paper x+xdot": Tissue(Law.of(["x", "xdot", "xddot"]), 350.0, 3.0, 0.05),
    "paper x^3+xdot^2": Tissue(Law.of(["x^3", "xdot|xdot|", "xddot"]), 8e6, 60.0, 0.05),
    "hardening x+x^3": Tissue(Law.of(["x", "x^3", "xdot", "xddot"]), 200.0, 5e6, 3.0, 0.05),
    "friction+offset": Tissue(
        Law.of(["x", "xdot", "sign(xdot)", "xddot", "offset"]), 350.0, 3.0, 0.1, 0.05, 0.2
    ),
    "Hunt-Crossley": Tissue(
        Law.of(["contact", "contact*xdot", "xddot"]).bind({"n": 1.5, "x0": 1e-3}),
        5000.0,
        3e4,
        0.05,
    ),
    "one branch": Tissue(
        Law.of(["x", "maxwell", "xdot", "xddot"]).bind({"tau1": 0.5}), 300.0, 200.0, 2.0, 0.05
    ),
    "two branches": Tissue(
        Law.of(["x", "maxwell", "maxwell", "xdot", "xddot"]).bind({"tau1": 0.1, "tau2": 2.0}),
        300.0,
        150.0,
        150.0,
        2.0,
        0.05,
    ),
}
#: three relaxation branches, resolvable in a 10 s session at 1 kHz
THREE_BRANCHES = Tissue(
    Law.of(["x", "maxwell", "maxwell", "maxwell", "xdot", "xddot"]).bind(
        {"tau1": 0.05, "tau2": 0.3, "tau3": 1.5}
    ),
    300.0,
    150.0,
    150.0,
    100.0,
    2.0,
    0.05,
)
