"""Every family of laws, end to end: simulate a forceps recording with the law, fit it
with that structure, write the parameter file, read it back, recover the parameters
within their posterior SDs, and check and render the written file on the display."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from tissuecli import formats
from tissuecli.app.play import check_file
from tissuecli.app.record import record
from tissuecli.core.errors import RenderError
from tissuecli.core.flags import NONFINITE
from tissuecli.core.terms import Law, Term
from tissuecli.core.tissue import Tissue
from tissuecli.formats.params import read_fitted, tissue_to_dict, write_params
from tissuecli.identify.outcome import fit_session
from tissuecli.render import PAPER_DISPLAY, Controller, check, simulate_offline
from tissuecli.render.controller import tracking_bound
from tissuecli.render.law import Branch, split_law
from tissuecli.sim.finger import OperatorForce
from tissuecli.sim.synth import CLOCK_HZ, ForcepsModel, Sensors, random_session

from ..conftest import assert_clean_error, tissuecli_here

#: A recovered parameter lies within this many posterior SDs of the truth. The posterior
#: is Gaussian to a good approximation here, so 4 SD fails a correct fit with
#: probability 6e-5 per parameter (about 2e-3 over the 30 parameters below, and the
#: seeds are fixed); the Coulomb fit's smoothed sign and its noisy speed near rest bias
#: Fc and S by up to 3.2 SD, still inside.
MAX_SD = 4.0

#: The families, each with the law as ``fit --forms`` writes it and a renderable truth:
#: the paper's form, hardening, dry friction with a sensor offset, Hunt-Crossley
#: contact, one relaxation branch (the standard linear solid) and two. Time constants
#: lie within what an 8 s session resolves (below a third of it).
FAMILIES = {
    "paper": (Tissue(Law.paper("x", "xdot"), 350.0, 3.0, 0.05), "x+xdot+xddot"),
    "hardening": (
        Tissue(Law.of(["x", "x^3", "xdot", "xddot"]), 300.0, 1e7, 3.0, 0.05),
        "x+x^3+xdot+xddot",
    ),
    "friction": (
        Tissue(Law.of(["x", "xdot", "sign(xdot)", "xddot", "offset"]), 350.0, 3.0, 0.2, 0.05, 0.1),
        "x+xdot+sign(xdot)+xddot+offset",
    ),
    "contact": (
        Tissue(
            Law.of(["contact", "contact*xdot", "xddot"]).bind({"n": 1.5, "x0": 3e-4}),
            8e3,
            4e3,
            0.05,
        ),
        "contact+contact*xdot+xddot",
    ),
    "sls": (
        Tissue(
            Law.of(["x", "maxwell", "xdot", "xddot"]).bind({"tau1": 1.0}), 400.0, 150.0, 2.0, 0.05
        ),
        "x+maxwell+xdot+xddot",
    ),
    "two branches": (
        Tissue(
            Law.of(["x", "maxwell", "maxwell", "xdot", "xddot"]).bind({"tau1": 0.15, "tau2": 2.0}),
            400.0,
            80.0,
            100.0,
            2.0,
            0.05,
        ),
        "x+maxwell+maxwell+xdot+xddot",
    ),
}


def _recovered(path, truth: Tissue) -> Tissue:
    """Read the written file back; assert every coefficient and shape parameter within
    MAX_SD posterior SDs of the truth."""
    fitted, cov, _ = read_fitted(path)
    assert fitted.law.name == truth.law.name and cov is not None
    doc = json.loads(path.read_text())
    sd = np.array([entry["sd"] for entry in doc["law"]["terms"]])
    np.testing.assert_allclose(np.sqrt(np.diag(cov)), sd, rtol=1e-6)
    z = (fitted.coef - truth.coef) / sd
    assert np.all(np.abs(z) < MAX_SD), dict(zip(truth.law.symbols, np.round(z, 2), strict=True))
    for entry in doc["law"].get("shape", []):
        name = entry["name"]
        err = (entry["mean"] - truth.law.shape[name]) / entry["sd"]
        assert abs(err) < MAX_SD, (name, entry, truth.law.shape[name])
    return fitted


def _renders_offline(tissue: Tissue) -> None:
    """The check accepts the tissue, and 3 s of presses on the offline loop stay finite and
    within the tracking bound plus the check's soft gap and the play's 0.4 mm allowance."""
    res = check(tissue)
    assert res.renderable, res.reasons
    out = simulate_offline(tissue, OperatorForce(seed=2), duration_s=3.0, gains=res.gains)
    assert not np.any(out["flags"] & NONFINITE)
    assert out["x"].max() > 1e-3  # the finger pressed into the tissue
    ctrl = Controller(tissue, PAPER_DISPLAY, 1000.0, res.gains)
    depths = np.linspace(0.0, out["x"].max(), 51)
    k_min = min(ctrl.local_stiffness(float(x)) for x in depths)
    bound = tracking_bound(
        res.gains.M, PAPER_DISPLAY.Mp, np.abs(out["ap"]).max(), k_min, PAPER_DISPLAY.resolution
    )
    assert np.abs(out["e"]).max() < bound + res.soft_gap + 4e-4


@pytest.mark.parametrize("family", list(FAMILIES))
def test_every_family_round_trips_and_renders(family, tmp_path):
    truth, forms = FAMILIES[family]
    session, _ = random_session(truth, seed=3, duration_s=8.0)
    outcome = fit_session(session, forms=forms)
    path = tmp_path / "p.json"
    write_params(path, outcome)
    fitted = _recovered(path, truth)
    result = check_file(path)
    assert result.renderable, result.reasons
    # what the check assumed of the terms beyond the paper's is said, and nothing dropped
    said = " ".join(result.assumptions)
    for t in fitted.law.terms:
        if t.name in ("contact", "contact*xdot", "sign(xdot)", "offset"):
            assert t.symbol in said or t.name in said, (t.name, said)
        if t.name == "maxwell":
            assert t.symbol in said
    _renders_offline(fitted)


def test_play_check_on_the_command_line_names_the_assumptions(tmp_path):
    path = tmp_path / "sls.json"
    path.write_text(json.dumps(tissue_to_dict(FAMILIES["sls"][0])))
    out = tissuecli_here("play", str(path), "--check")
    assert out.returncode == 0, out.stderr
    assert "assumed: relaxation branches Km1" in out.stdout
    assert "instantaneous stiffness adds 150 N/m" in out.stdout


# --------------------------------------------------------------------------- the controller


def test_branch_states_follow_the_exact_recursion():
    """A relaxation branch stepped frame by frame with varying dt is the core's exact
    recursion: r' = x' - r / tau, with x linear between samples."""
    from tissuecli.core.terms import relaxation

    rng = np.random.default_rng(0)
    x = np.cumsum(rng.normal(0, 1e-4, 400))
    br = Branch(Km=100.0, tau=0.05)
    r, out = 0.0, []
    prev = x[0]
    for xi in x:
        r = br.step(r, xi - prev, 1e-3)
        prev = xi
        out.append(r)
    expected, _ = relaxation(x, 1e-3, 0.05)
    np.testing.assert_allclose(out, expected, rtol=1e-9, atol=1e-15)


def test_the_reference_model_relaxes_under_a_held_force():
    """Held by a constant force, the controller's model of a standard linear solid creeps
    from F / (K + Km) towards F / K with the creep time constant tau (K + Km) / K."""
    K, Km, tau, force = 400.0, 150.0, 0.2, 1.0
    tissue = Tissue(Law.of(["x", "maxwell", "xdot", "xddot"]).bind({"tau1": tau}), K, Km, 5.0, 0.05)
    res = check(tissue)
    ctrl = Controller(tissue, PAPER_DISPLAY, 1000.0, res.gains)
    ctrl.start(0.0, 0.0)
    # a piston held still at the equilibrium of display and force: the observed force is
    # constant, so the model sees a step of it
    xp = 2e-3
    volts = math.sqrt(max(force - PAPER_DISPLAY.Kp * xp, 0.0) / PAPER_DISPLAY.alpha)
    ctrl.x = xp
    ctrl.start(xp, volts)
    ctrl.xm = 0.0
    seen = []
    for _ in range(3000):
        seen.append(ctrl.update(xp, volts).xm)
    seen = np.array(seen)
    creep = tau * (K + Km) / K
    t = np.arange(1, 3001) * 1e-3
    late = t > 0.2  # after the inertial transient (M / S, S / K: tens of ms)
    gap = force / K - force / (K + Km)
    expected = force / K - gap * np.exp(-t / creep)
    # the parallel damper S delays the creep by about S / (K + Km) = 9 ms, a few % of the
    # gap early on; the model settles on F / K
    np.testing.assert_allclose(seen[late], expected[late], atol=0.05 * gap)
    assert abs(seen[-1] - force / K) < 1e-3 * gap + 1e-7


# --------------------------------------------------------------------------- refusals


class _Hereditary(Term):
    """A term with a memory that is not a relaxation branch (for the refusal test)."""

    name, symbol, unit, label, role, variable = "hereditary", "H1", "N/m", "h", "relaxation", "h"
    memory = True

    def __call__(self, u):
        return np.asarray(u, dtype=float)

    def derivative(self, u):
        return np.ones_like(np.asarray(u, dtype=float))


def test_a_term_the_controller_cannot_carry_is_refused_by_name():
    tissue = Tissue(Law((Law.of(["x"]).terms[0], _Hereditary())), 400.0, 100.0)
    parts = split_law(tissue)
    assert parts.refusals and "hereditary (H1)" in parts.refusals[0]
    res = check(tissue)
    assert not res.renderable and any("hereditary (H1)" in r for r in res.reasons)
    with pytest.raises(RenderError, match="hereditary"):
        Controller(tissue, PAPER_DISPLAY, 1000.0, res.gains)


def test_a_fluid_without_a_spring_is_refused_with_the_reason(tmp_path):
    """A Maxwell fluid (a relaxation branch and no spring) holds no grasp: after 1 s at
    tau = 0.2 s its force has all but gone, so a held 3.4 N is deeper than the stroke."""
    tissue = Tissue(Law.of(["maxwell", "xdot", "xddot"]).bind({"tau1": 0.2}), 800.0, 2.0, 0.05)
    res = check(tissue)
    assert not res.renderable
    assert any("deeper than the 15 mm stroke" in r for r in res.reasons)
    path = tmp_path / "fluid.json"
    path.write_text(json.dumps(tissue_to_dict(tissue)))
    assert_clean_error(tissuecli_here("play", str(path), "--check", "--port", "x"), "stroke")


def test_a_viscoelastic_release_that_pulls_is_refused():
    """A branch with a large Km tau is a strong damper on a release at hand speed: the
    tissue pulls the jaws and the solenoid would have to push over most of the depth."""
    tissue = Tissue(
        Law.of(["x", "maxwell", "xdot", "xddot"]).bind({"tau1": 0.5}), 300.0, 200.0, 2.0, 0.05
    )
    res = check(tissue)
    assert not res.renderable
    assert any("on release" in r for r in res.reasons)


# --------------------------------------------------------------------------- simulate forceps


@pytest.mark.parametrize("family", list(FAMILIES))
def test_simulated_forceps_streams_every_law(family, forceps, tmp_path):
    """``simulate forceps --params`` accepts every law and streams its physics."""
    truth, _ = FAMILIES[family]
    params = tmp_path / "p.json"
    params.write_text(json.dumps(tissue_to_dict(truth)))
    sim = forceps("--params", str(params), "--seed", "3")
    out = tmp_path / "r.h5"
    res = record(str(sim.link), out, "s1", duration_s=0.6)
    assert res.samples >= 550
    s = formats.read_session(out, raw=True)
    model = ForcepsModel(tissue=truth, seed=3)
    k = (s.meta["raw"]["raw/device_clock"] / (CLOCK_HZ / model.rate_hz)).round().astype(int)
    _, _, _, f = model.truth(k)
    sens = Sensors()
    bound_f = 5 * np.hypot(sens.force_noise_n, sens.calibration.force.gain / np.sqrt(12))
    assert np.max(np.abs(s.force - np.clip(f, *sens.force_range_n))) < bound_f


@pytest.mark.slow
def test_a_recorded_standard_linear_solid_round_trips(forceps, tmp_path):
    """The real thing for one family: the simulated forceps on a pseudo-terminal,
    ``record``, fit, the parameter file, and ``play --check`` of it."""
    truth, forms = FAMILIES["sls"]
    params = tmp_path / "truth.json"
    params.write_text(json.dumps(tissue_to_dict(truth)))
    sim = forceps("--params", str(params), "--seed", "5")
    out = tmp_path / "r.h5"
    record(str(sim.link), out, "s1", duration_s=8.0)
    outcome = fit_session(formats.read_session(out), forms=forms)
    path = tmp_path / "fit.json"
    write_params(path, outcome)
    _recovered(path, truth)
    check_out = tissuecli_here("play", str(path), "--check")
    assert check_out.returncode == 0, check_out.stderr
