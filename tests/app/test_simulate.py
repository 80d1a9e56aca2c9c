"""The simulated forceps' options, one class for the binary and the text simulator."""

from __future__ import annotations

import pytest

from tissuecli.app.simulate import SimulatedForceps
from tissuecli.core.errors import InputError
from tissuecli.core.tissue import DEFAULT_TISSUE


def test_simulated_forceps_defaults_are_the_commands() -> None:
    """The library's defaults are those `simulate forceps` shows in --help: an 8-bit ADC,
    5 mN of force noise, 5 um of position noise, the liver-like tissue at 1 kHz."""
    model = SimulatedForceps().model()
    assert model.sensors.bits == 8
    assert model.sensors.force_noise_n == pytest.approx(0.005)
    assert model.sensors.position_noise_m == pytest.approx(5e-6)
    assert model.rate_hz == 1000.0 and model.drift_ppm == 0.0
    assert model.tissue == DEFAULT_TISSUE


def test_simulated_forceps_carries_every_option(tmp_path) -> None:
    model = SimulatedForceps(
        rate_hz=250.0, adc_bits=12, force_noise_n=0.02, position_noise_m=1e-5,
        drift_ppm=40.0, seed=3,
    ).model()  # fmt: skip
    assert (model.rate_hz, model.drift_ppm, model.seed) == (250.0, 40.0, 3)
    assert (model.sensors.bits, model.sensors.force_noise_n) == (12, 0.02)
    assert model.sensors.position_noise_m == 1e-5
    with pytest.raises(InputError, match="does not exist"):
        SimulatedForceps(params=tmp_path / "missing.json").model()
