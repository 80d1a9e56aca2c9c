"""One device vocabulary: the forceps and the display are :class:`Device` classes in a
registry, and a new kind of device is one class and a registry entry, opened, checked
and read by the same handshake as theirs."""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

import numpy as np
import pytest

from tissuecli.core.errors import DeviceError
from tissuecli.hw import device as hw_device
from tissuecli.hw.device import (
    Device,
    Display,
    Forceps,
    TextLogger,
    device_class,
)
from tissuecli.hw.link import check_info, open_device
from tissuecli.hw.protocol import Encoder, Sample
from tissuecli.hw.text import Line

from ..app.fakedevice import TICKS, FakeForceps, good_info, sample_frames


def test_the_built_in_devices_are_registered_with_their_frames() -> None:
    assert device_class("forceps") is Forceps and Forceps.frame_type is Sample
    assert device_class("display") is Display and Display.frame_type is Encoder
    assert device_class("text-logger") is TextLogger and TextLogger.frame_type is Line
    with pytest.raises(DeviceError, match="known kinds: display, forceps, text-logger"):
        device_class("toaster")


@pytest.fixture
def thermometer(registered_device) -> type[Device]:
    """A new kind of device: one class, one registry entry (removed afterwards)."""

    class Thermometer(Device):
        kind = "thermometer"
        role = "a thermometer is read by a lab's own loop"
        frame_type = Sample
        required_info = ("rate_hz", "clock_hz", "range_c")

        @classmethod
        def check_info(
            cls, info: dict[str, Any], url: str, refuse: Callable[..., DeviceError], **o: Any
        ) -> None:
            super().check_info(info, url, refuse)
            span = info.get("range_c", hw_device.MISSING)
            if not (isinstance(span, list) and len(span) == 2):
                raise refuse("range_c", span, "[lowest, highest] in degrees C")

        def limits(self) -> dict[str, Any]:
            return {"range_c": (self.info or {}).get("range_c")}

    return registered_device(Thermometer)


def _info(**changes: Any) -> dict[str, Any]:
    return good_info(device="thermometer", range_c=[-20, 120], **changes)


def test_a_new_device_is_one_class_and_a_registry_entry(thermometer) -> None:
    seqs = np.arange(200)
    with FakeForceps(_info(), sample_frames(seqs, seqs * TICKS)) as fake:
        dev = device_class("thermometer")(fake.path).open(require_info=True)
        with dev:
            assert isinstance(dev, thermometer) and dev.limits() == {"range_c": [-20, 120]}
            dev.start()
            frames: list[Any] = []
            deadline = time.monotonic() + 5.0
            while len(frames) < 200 and time.monotonic() < deadline:
                frames += dev.read()
            dev.stop()
        assert [f.seq for f in frames] == list(range(200))


def test_the_handshake_checks_the_new_kind_as_its_class_says(thermometer) -> None:
    with pytest.raises(DeviceError, match=r"no Info range_c; it must be \[lowest, highest\]"):
        check_info(good_info(device="thermometer"), "/dev/x", "thermometer")
    # another kind answering is refused with what this one is for
    with FakeForceps(good_info(), []) as fake:
        with pytest.raises(DeviceError, match="not a thermometer; a thermometer is read"):
            open_device(fake.path, "thermometer")


def test_the_forceps_checks_are_its_class_own() -> None:
    with pytest.raises(DeviceError, match="no Info adc_bits"):
        check_info(good_info(adc_bits=...), "/dev/x", "forceps")
    check_info({"rate_hz": 1000.0}, "/dev/x", "display")  # a display needs no ADC
