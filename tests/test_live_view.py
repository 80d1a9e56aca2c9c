"""The live view while recording: /api/state, the page and its assets, clients that
stall or vanish, bad addresses, and (slow) a real headless browser."""

from __future__ import annotations

import json
import math
import socket
import threading
import time
import urllib.request
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from tissuecli import formats
from tissuecli.core.errors import InputError
from tissuecli.live.server import ASSETS, LiveServer, load_asset, parse_address
from tissuecli.live.state import LOOP_S, TRACE_POINTS, TRACE_S, LiveState

from .conftest import assert_clean_error, popen, tissuecli

ROOT = Path(__file__).resolve().parents[1]
STATUS_KEYS = {"elapsed_s", "samples", "rate_hz", "bad_frames", "lost_frames", "file_bytes"}
TOP_KEYS = {
    "schema",
    "session",
    "running",
    "samples_seen",
    "server_monotonic_s",
    "newest_sample_monotonic_s",
    "sample_age_s",
    "status",
    "traces",
    "loop",
    "estimate",
}


def _get(url: str, timeout: float = 5.0) -> bytes:
    with urllib.request.urlopen(url, timeout=timeout) as response:
        return response.read()


def _state(base: str) -> dict:
    return json.loads(_get(base + "api/state"))


def _grasps(rate: float, seconds: float, start: float = 0.0) -> SimpleNamespace:
    """A block of squeezes at 1 Hz: closure 0-5 mm, force 400 N/m x + 3 N s/m xdot."""
    t = start + np.arange(round(rate * seconds)) / rate
    x = 2.5e-3 * (1 - np.cos(2 * np.pi * t))
    v = 2.5e-3 * 2 * np.pi * np.sin(2 * np.pi * t)
    return SimpleNamespace(time=t, position=x, force=400 * x + 3 * v, host_time=t.copy())


def _check_schema(state: dict) -> None:
    assert set(state) == TOP_KEYS
    assert state["schema"] == 1
    assert set(state["status"]) == STATUS_KEYS
    tr, lp = state["traces"], state["loop"]
    assert tr["window_s"] == TRACE_S
    n = len(tr["time_s"])
    assert len(tr["position_m"]) == len(tr["force_n"]) == n <= TRACE_POINTS
    m = len(lp["time_s"])
    assert len(lp["position_m"]) == len(lp["force_n"]) == len(lp["closing"]) == m
    assert all(isinstance(c, bool) for c in lp["closing"])
    if n:
        assert np.all(np.diff(tr["time_s"]) > 0)
        assert tr["time_s"][-1] - tr["time_s"][0] <= TRACE_S
        assert lp["time_s"][0] >= lp["start_s"] - 1e-9
        assert tr["time_s"][-1] - lp["start_s"] <= LOOP_S + 0.05  # to a bucket's start


# -- the state alone -------------------------------------------------------------------


def test_state_decimates_the_newest_window_and_splits_the_loop_by_direction():
    state = LiveState("s", capacity=1 << 16)
    for k in range(30):  # 15 s at 2 kHz in blocks of 0.5 s
        state.append(_grasps(2000, 0.5, start=0.5 * k))
    doc = state.snapshot()
    _check_schema(doc)
    tr, lp = doc["traces"], doc["loop"]
    assert doc["samples_seen"] == 30_000 and doc["status"]["samples"] == 30_000
    # the last 10 s, newest last; bucket means of the 1 Hz squeeze stay on it
    assert tr["time_s"][-1] == pytest.approx(15, abs=5e-3)  # a bucket is 7 ms
    assert tr["time_s"][0] == pytest.approx(5, abs=0.02)
    t = np.array(tr["time_s"])
    np.testing.assert_allclose(tr["position_m"], 2.5e-3 * (1 - np.cos(2 * np.pi * t)), atol=2e-5)
    # the loop begins where the force last rose through 10 % of its range (0.1 s after
    # each squeeze begins), at least 1 s ago: the rise at 14.1 s is too recent
    assert lp["start_s"] == pytest.approx(13.1, abs=0.03)
    x = np.array(lp["position_m"])
    closing = np.array(lp["closing"])
    rising = np.gradient(x) > 0
    inside = slice(10, -10)  # the ends of the smoothing
    assert np.mean(closing[inside] == rising[inside]) > 0.97
    assert closing.any() and not closing.all()


def test_the_ring_keeps_the_newest_samples_across_its_wrap():
    state = LiveState("s", capacity=3000)
    for k in range(7):
        state.append(_grasps(1000, 0.7, start=0.7 * k))  # 4900 samples through 3000
    big = _grasps(1000, 5.0, start=4.9)  # a block larger than the ring
    state.append(big)
    doc = state.snapshot()
    assert doc["samples_seen"] == 9900
    t = doc["traces"]["time_s"]
    # at most a third of the ring is read, the newest sample last and in order
    assert t[-1] == pytest.approx(big.time[-1]) and np.all(np.diff(t) > 0)
    assert t[-1] - t[0] == pytest.approx(0.999, abs=1e-3)
    np.testing.assert_allclose(doc["traces"]["force_n"], big.force[-len(t) :], atol=1e-6)


def test_an_empty_state_is_a_valid_document_and_json_has_no_nan():
    state = LiveState("s")
    doc = json.loads(state.document())
    _check_schema(doc)
    assert doc["estimate"] is None and doc["newest_sample_monotonic_s"] is None
    state.set_estimate(
        SimpleNamespace(as_dict=lambda: {"law": "x+xdot", "mean": [1.0], "ci95": [[0.5, 2]]})
    )
    state.set_status(SimpleNamespace(elapsed_s=1.0, samples=5, rate_hz=math.nan))
    assert json.loads(state.document(max_age_s=0))["estimate"]["law"] == "x+xdot"


# -- the server on its own -------------------------------------------------------------


@pytest.fixture
def served():
    state = LiveState("bench")
    with LiveServer(state) as server:
        yield state, server.url


def test_the_page_and_its_assets_come_from_the_package(served):
    _, url = served
    page = _get(url).decode()
    for path in ("live.js", "live.css", "uPlot.iife.min.js", "uPlot.min.css"):
        assert f'"{path}"' in page  # referenced relatively: nothing from elsewhere
        assert _get(url + path) == load_asset(ASSETS["/" + path][0])
    assert "http" not in page.replace("http-equiv", "")
    assert "MIT" in load_asset("uPlot.LICENSE").decode()
    with pytest.raises(urllib.error.HTTPError) as err:
        _get(url + "../pyproject.toml")
    assert err.value.code == 404


def test_package_data_covers_every_asset():
    """pyproject's package data names every file the server loads, and nothing else is in
    the assets folder that the page would miss."""
    import fnmatch

    tomllib = pytest.importorskip("tomllib")  # Python 3.11+

    globs = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"][
        "package-data"
    ]["tissuecli"]
    folder = ROOT / "tissuecli" / "live" / "assets"
    files = {f"live/assets/{p.name}" for p in folder.iterdir()}
    assert files == {f"live/assets/{name}" for name, _ in ASSETS.values()}
    for name in files:
        assert any(fnmatch.fnmatch(name, g) for g in globs), name


@pytest.mark.slow
def test_the_wheel_carries_the_page(tmp_path):
    """Built as pip builds it (setuptools from the registry), the wheel holds every file
    the server loads."""
    import subprocess
    import sys
    import zipfile

    subprocess.run(
        [sys.executable, "-m", "pip", "wheel", "--no-deps", "-q", "-w", str(tmp_path), str(ROOT)],
        check=True, capture_output=True, timeout=600,
    )  # fmt: skip
    (wheel,) = tmp_path.glob("tissuecli-*.whl")
    names = set(zipfile.ZipFile(wheel).namelist())
    for name, _ in ASSETS.values():
        assert f"tissuecli/live/assets/{name}" in names


def test_a_stalled_or_vanished_client_does_not_block_the_others(served):
    state, url = served
    host, port = parse_address(url.removeprefix("http://").rstrip("/"))
    # one sends half a request and waits; one asks and never reads, with a tiny buffer;
    # one asks and hangs up at once
    half = socket.create_connection((host, port))
    half.sendall(b"GET /api/sta")
    mute = socket.socket()
    mute.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1024)
    mute.connect((host, port))
    mute.sendall(b"GET /api/state HTTP/1.1\r\nHost: x\r\n\r\n" * 200)
    gone = socket.create_connection((host, port))
    gone.sendall(b"GET /api/state HTTP/1.1\r\nHost: x\r\n\r\n")
    gone.close()
    feeding = threading.Event()

    def feed() -> None:
        k = 0
        while not feeding.is_set():
            state.append(_grasps(1000, 0.01, start=0.01 * k))
            k += 1
            time.sleep(0.01)

    feeder = threading.Thread(target=feed)
    feeder.start()
    try:
        seen = []
        for _ in range(20):
            doc = _state(url)
            seen.append(doc["samples_seen"])
        assert seen[-1] > seen[0]  # numbers change while the others hang
    finally:
        feeding.set()
        feeder.join()
        half.close()
        mute.close()


def test_a_port_in_use_is_refused_in_one_line():
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        with pytest.raises(InputError, match=f"--live 127.0.0.1:{port}: the port is in use"):
            LiveServer(LiveState(), "127.0.0.1", port)


@pytest.mark.parametrize(
    ("text", "expected"),
    [("127.0.0.1:8050", ("127.0.0.1", 8050)), (":0", ("127.0.0.1", 0)), ("[::1]:80", ("::1", 80))],
)
def test_addresses_parse(text, expected):
    assert parse_address(text) == expected


@pytest.mark.parametrize("text", ["8050", "localhost", "host:port", "127.0.0.1:70000", ""])
def test_bad_addresses_are_refused(text):
    with pytest.raises(InputError, match="--live expects HOST:PORT"):
        parse_address(text)


# -- record --live ---------------------------------------------------------------------


def _url_of(proc) -> str:
    line = proc.stdout.readline()
    assert line.startswith("live view: http://127.0.0.1:"), line + proc.stderr.read()
    return line.split(": ", 1)[1].strip()


def test_record_live_serves_changing_numbers_and_stays_lossless(forceps, tmp_path):
    sim = forceps("--seed", "5")
    out = tmp_path / "g.h5"
    proc = popen("record", "--port", str(sim.link), "--out", str(out), "--session", "s",
                 "--duration", "4", "--live", "--quiet")  # fmt: skip
    try:
        url = _url_of(proc)
        assert "tissuecli live view" in _get(url).decode()
        docs = []
        while len(docs) < 2 or docs[-1]["samples_seen"] < 1500:
            doc = _state(url)
            if doc["samples_seen"]:
                docs.append(doc)
            time.sleep(0.1)
        for doc in docs:
            _check_schema(doc)
        first, last = docs[0], docs[-1]
        assert last["samples_seen"] > first["samples_seen"]
        assert last["status"]["elapsed_s"] > first["status"]["elapsed_s"]
        assert last["traces"]["time_s"][-1] > first["traces"]["time_s"][-1]
        assert last["session"] == "s" and last["running"]
        # the status is the recorder's: samples at 1 kHz, no fault
        st = last["status"]
        assert st["rate_hz"] == pytest.approx(1000, rel=0.2)  # start-up included
        assert st["samples"] == last["samples_seen"]
        assert st["lost_frames"] == st["bad_frames"] == 0
        assert 0 <= last["sample_age_s"] < 1.0
        # SI: closure in metres (the simulator squeezes 0.2-7 mm), force in newtons
        assert 0 < max(last["traces"]["position_m"]) < 0.01
        assert 0 < max(last["traces"]["force_n"]) < 10
        assert proc.wait(timeout=30) == 0
    finally:
        proc.kill()
        proc.wait()
    row = formats.list_sessions(out)[0]
    assert (row["samples"], row["frames_lost"]) == (4000, 0)
    with pytest.raises(OSError):
        _get(url, timeout=2)  # the server stopped with the recording


def test_record_live_refuses_a_port_in_use_before_touching_anything(tmp_path):
    out = tmp_path / "g.h5"
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        result = tissuecli("record", "--port", str(tmp_path / "no-device"), "--out", str(out),
                           "--live", f"127.0.0.1:{port}")  # fmt: skip
    assert_clean_error(result, "the port is in use")
    assert not out.exists()


@pytest.mark.parametrize("live", ["8050", "127.0.0.1:http", "127.0.0.1:99999"])
def test_record_refuses_a_bad_live_address_in_one_line(tmp_path, live):
    result = tissuecli("record", "--port", str(tmp_path / "no-device"), "--out",
                       str(tmp_path / "g.h5"), "--live", live)  # fmt: skip
    assert_clean_error(result, "--live expects HOST:PORT", repr(live))
