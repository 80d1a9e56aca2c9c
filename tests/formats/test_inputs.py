"""JSON inputs (parameter, calibration and display profile files): every read is validated,
within size and depth limits, and every bad file is one line naming the file, the item
and what is wrong, from the library and from every command that reads one."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import pytest
from click.testing import CliRunner
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from tests.conftest import assert_clean_error, tissuecli, tissuecli_here
from tissuecli.cli import cli
from tissuecli.core.errors import InputError
from tissuecli.core.terms import TERMS, Law
from tissuecli.core.tissue import DEFAULT_TISSUE, Tissue
from tissuecli.formats.jsonfile import MAX_BYTES, MAX_DEPTH, SHOW_CHARS, read_json
from tissuecli.formats.params import (
    FORMAT_VERSION,
    parameter_range,
    read_calibration,
    read_profile,
    read_tissue,
    tissue_to_dict,
)
from tissuecli.render import PAPER_DISPLAY, check

VALID_PARAMS = tissue_to_dict(DEFAULT_TISSUE)
#: the same tissue in a version 1 file, which this tissuecli still reads
VALID_PARAMS_V1 = {
    "format": "tissuecli-parameters",
    "version": 1,
    "model": {"f0": "x", "f1": "xdot"},
    "parameters": {
        "K": {"mean": 350.0, "unit": "N/m"},
        "S": {"mean": 3.0, "unit": "N s/m"},
        "M": {"mean": 0.05, "unit": "kg"},
    },
}
VALID_CAL = {
    "force": {"gain": 0.0235294, "offset": 2.0117647, "unit": "N"},
    "position": {"gain": 6.0784e-05, "offset": 0.0072804, "unit": "m"},
}
VALID_PROFILE = PAPER_DISPLAY.as_dict()
READERS = {"parameter": read_tissue, "calibration": read_calibration, "profile": read_profile}

#: An error line may name the file (its path) and echo at most SHOW_CHARS of a value;
#: the rest is a fixed sentence. Generous, but far below an echoed megabyte.
MAX_MESSAGE = 400


def _write(tmp: Path, content: bytes | str | dict, name: str = "f.json") -> Path:
    path = tmp / name
    if isinstance(content, dict):
        content = json.dumps(content)
    path.write_bytes(content.encode() if isinstance(content, str) else content)
    return path


def _one_line(message: str, path: Path) -> None:
    assert "\n" not in message and "\r" not in message, message
    assert len(message) <= len(str(path)) + MAX_MESSAGE, message[:500]


# --------------------------------------------------------------------------- examples


def _params(base: dict[str, Any] = VALID_PARAMS_V1, **changes: Any) -> dict[str, Any]:
    """A copy of ``base`` with items changed: ``parameters__K__mean=1`` sets
    ``doc["parameters"]["K"]["mean"]``; a number in the path indexes a list."""
    doc = json.loads(json.dumps(base))
    for path, value in changes.items():
        *head, last = path.split("__")
        node = doc
        for key in head:
            node = node[int(key)] if key.isdigit() else node[key]
        node[int(last) if last.isdigit() else last] = value
    return doc


def _v2(**changes: Any) -> dict[str, Any]:
    return _params(VALID_PARAMS, **changes)


@pytest.mark.parametrize(
    ("content", "needles"),
    [
        (b"\x89HDF\r\n\x1a\n\x00\x00binary", ["is an HDF5 file, not JSON"]),
        (b'{"model": "\xff\xfe"}', ["not UTF-8", "0xff", "offset 11"]),
        ("[" * 100_000 + "]" * 100_000, [f"more than {MAX_DEPTH} deep"]),
        (
            '{"model": {"f0": "x", "f1": "xdot"}, "parameters": {"K": {"mean": '
            + "9" * 400
            + '}, "S": 3, "M": 0.05}}',
            ["parameters.K.mean", "400-digit integer", "not a finite number"],
        ),
        (_params(parameters__K__mean=1e300), ["parameters.K.mean", "1e+300", "<= 1e+06 N/m"]),
        (_params(version=99), ["written by a newer tissuecli", "version 99"]),
        (_params(version=True), ["version", "whole number"]),
        (_params(format="tissuecli-display"), ["is a display profile file"]),
        (_params(model__f0="a" * 500_000), ["model.f0", "is not a stiffness form", "..."]),
        (_params(parameters__S__unit="N s/mm"), ["parameters.S.unit", "'N s/m'"]),
        (_params(parameters__M__mean=-0.01), ["parameters.M.mean", ">= 0"]),
        (_params(parameters__K__mean="350"), ["parameters.K.mean", "must be a number"]),
        (_params(parameters__K__sd=-1), ["parameters.K.sd", ">= 0"]),
        (_params(paramters={}), ["paramters", "unknown key"]),
        (_params(warnings=[1]), ["warnings[0]", "must be a string"]),
        (_params(data=[]), ["data", "must be an object"]),
        ('{"model": {"f0": "x", "f1": "xdot"}, "model": {}}', ["'model' appears twice"]),
        ('{"a": NaN}', ["a = NaN", "not a finite number"]),
        ('{"a": [1, -Infinity]}', ["a[1] = -Infinity"]),
        ('{"a": 1e999}', ["a = 1e999"]),
        ("[1, 2]", ["must hold a JSON object", "an array"]),
        ('{"a": ', ["not valid JSON", "line 1"]),
        ("", ["not valid JSON"]),
        (_v2(law__terms__0__mean=1e300), ["law.terms[0].mean", "<= 1e+06 N/m"]),
        (_v2(law__terms__1__term="xdot^3"), ["law.terms[1].term", "is not a term"]),
        (_v2(law__terms__2__unit="g"), ["law.terms[2].unit", "'kg'"]),
        (_v2(law__terms=[]), ["law.terms", "non-empty"]),
        (_v2(law__terms__1__term="x"), ["law.terms[1].term", "appears twice"]),
        (_v2(law__terms__0__mean=-1.0), ["law.terms[0].mean", ">= 0"]),
        (
            _v2(law={"terms": [{"term": "offset", "mean": -2e3}]}),
            ["law.terms[0].mean", ">= -1000 N"],
        ),
    ],
)
def test_bad_parameter_files_are_one_line_naming_the_item(tmp_path, content, needles):
    path = _write(tmp_path, content)
    with pytest.raises(InputError) as info:
        read_tissue(path)
    message = str(info.value)
    _one_line(message, path)
    assert message.startswith(f"parameter file {path}"), message
    assert "a" * SHOW_CHARS not in message  # values are echoed cut short
    for needle in needles:
        assert needle in message, message


def test_too_big_a_file_is_refused_before_it_is_parsed(tmp_path):
    path = _write(tmp_path, '{"note": "' + "a" * MAX_BYTES + '"}')
    with pytest.raises(InputError, match="larger than 1 MiB") as info:
        read_json(path, "parameter")
    _one_line(str(info.value), path)


def test_missing_directory_and_unreadable_files(tmp_path):
    for path, needle in ((tmp_path / "none.json", "does not exist"), (tmp_path, "directory")):
        with pytest.raises(InputError, match=needle):
            read_tissue(path)


def test_the_minimal_and_the_written_files_are_read_back(tmp_path):
    minimal = {
        "model": {"f0": "x^3", "f1": "xdot^2"},
        "parameters": {"K": 1e8, "S": {"mean": 2.0}, "M": {"mean": 0.0, "unit": "kg"}},
    }
    t = read_tissue(_write(tmp_path, minimal))
    assert (t.law.name, t.K3, t.S2, t.M) == ("x^3+xdot|xdot|+xddot", 1e8, 2.0, 0.0)
    assert read_tissue(_write(tmp_path, VALID_PARAMS)) == DEFAULT_TISSUE
    assert read_tissue(_write(tmp_path, VALID_PARAMS_V1)) == DEFAULT_TISSUE
    offset = {"law": {"terms": [{"term": "x", "mean": 100}, {"term": "offset", "mean": -0.3}]}}
    assert read_tissue(_write(tmp_path, offset)).F0 == -0.3
    assert read_calibration(_write(tmp_path, VALID_CAL)).force.gain == 0.0235294
    assert read_profile(_write(tmp_path, VALID_PROFILE)) == PAPER_DISPLAY
    # the limits themselves are accepted: a range is inclusive
    model = Law.paper("x", "xdot^2")
    edge = Tissue(model, *(parameter_range(t) for t in model.terms))
    assert read_tissue(_write(tmp_path, tissue_to_dict(edge))) == edge


def test_parameter_ranges_are_a_kilonewton_at_small_jaw_motion():
    expected = {
        "x": 1e6,
        "x^3": 1e12,
        "xdot": 1e5,
        "xdot|xdot|": 1e7,
        "sign(xdot)": 1e3,
        "xddot": 1e3,
        "offset": 1e3,
    }
    for name, top in expected.items():
        # dry friction is tanh(v / 1 mm/s): at 10 mm/s it is 1 - 4e-9
        assert parameter_range(TERMS[name]) == pytest.approx(top, rel=1e-8), name


@pytest.mark.parametrize(
    ("doc", "needles"),
    [
        ({"force": VALID_CAL["force"]}, ["position", "is missing"]),
        ({**VALID_CAL, "force": {"gain": 0}}, ["force.gain", "too small"]),
        ({**VALID_CAL, "force": {"gain": 1e6}}, ["force.gain", "<= 10 N/count"]),
        ({**VALID_CAL, "position": {"gain": 1e-5, "unit": "mm"}}, ["position.unit", "'m'"]),
        ({**VALID_CAL, "position": {"gain": 1e-5, "ofset": 0}}, ["position.ofset", "unknown"]),
        ({**VALID_CAL, "version": 2}, ["written by a newer tissuecli"]),
        ({**VALID_CAL, "force": [1, 2]}, ["force", "must be an object"]),
    ],
)
def test_bad_calibration_files(tmp_path, doc, needles):
    path = _write(tmp_path, doc)
    with pytest.raises(InputError) as info:
        read_calibration(path)
    message = str(info.value)
    _one_line(message, path)
    assert message.startswith(f"calibration file {path}"), message
    for needle in needles:
        assert needle in message, message


@pytest.mark.parametrize(
    ("doc", "needles"),
    [
        ({"Mp": 83.35}, ["Mp = 83.35", "(0.001, 10]"]),  # grams for kilograms
        ({"stroke": {"value": 15, "unit": "m"}}, ["stroke", "(0.0001, 1]"]),
        ({"resolution": 1e-3, "stroke": 0.015}, ["fewer than 100 steps"]),
        ({"version": 7}, ["written by a newer tissuecli"]),
        ({"format": "tissuecli-parameters"}, ["is it a display profile"]),
        ({"Kp": {"value": 300, "unit": "N/m", "sd": 1}}, ["Kp must be a number or"]),
        ({"b" * 10_000: 1}, ["unknown key", "..."]),
    ],
)
def test_bad_profile_files(tmp_path, doc, needles):
    path = _write(tmp_path, doc)
    with pytest.raises(InputError) as info:
        read_profile(path)
    message = str(info.value)
    _one_line(message, path)
    assert message.startswith(f"display profile file {path}"), message
    for needle in needles:
        assert needle in message, message


# --------------------------------------------------------------------------- generated files

KEYS = st.sampled_from(
    ["model", "parameters", "f0", "f1", "K", "S", "M", "mean", "sd", "ci95", "unit", "format",
     "version", "force", "position", "gain", "offset", "Mp", "Kp", "alpha", "v_max", "stroke",
     "resolution", "b", "value", "data", "warnings", "note"]
) | st.text(max_size=8)  # fmt: skip
#: JSON numbers written as text: what json.dumps cannot write, or writes as non-JSON
NUMBER_TEXT = st.sampled_from(
    ["NaN", "Infinity", "-Infinity", "1e999", "-1e400", "9" * 400, "-" + "1" * 5000, "1e-400",
     "0.0", "-0", "1E+2", "123456789012345678901234567890"]
)  # fmt: skip
LEAF = (
    st.none()
    | st.booleans()
    | st.integers(-(10**30), 10**30)
    | st.floats(allow_nan=True, allow_infinity=True)
    | st.text(max_size=12)
    | st.sampled_from(
        [
            "x",
            "x^3",
            "xdot",
            "xdot^2",
            "N/m",
            "kg",
            "N s/m",
            "tissuecli-parameters",
            "tissuecli-display",
            "tissuecli-calibration",
            "\ud800",
            "a\u0000b",
        ]
    )  # fmt: skip
)
VALUE = st.recursive(
    LEAF, lambda inner: st.lists(inner, max_size=4) | st.dictionaries(KEYS, inner, max_size=5),
    max_leaves=25,
)  # fmt: skip
VALID = st.sampled_from([VALID_PARAMS, VALID_CAL, VALID_PROFILE])


def _paths(doc: Any, prefix: tuple = ()) -> list[tuple]:
    out = [prefix]
    if isinstance(doc, dict):
        for k, v in doc.items():
            out += _paths(v, (*prefix, k))
    elif isinstance(doc, list):
        for i, v in enumerate(doc):
            out += _paths(v, (*prefix, i))
    return out


@st.composite
def mutated(draw: st.DrawFn) -> str:
    """A valid document with one item replaced, removed or added."""
    doc = json.loads(json.dumps(draw(VALID)))
    path = draw(st.sampled_from(_paths(doc)))
    if not path:
        return json.dumps(draw(VALUE))
    node = doc
    for key in path[:-1]:
        node = node[key]
    action = draw(st.sampled_from(["replace", "delete", "add"]))
    if action == "delete":
        del node[path[-1]]
    elif action == "add" and isinstance(node, dict):
        node[draw(KEYS)] = draw(VALUE)
    else:
        node[path[-1]] = draw(VALUE)
    return json.dumps(doc)


@st.composite
def with_raw_number(draw: st.DrawFn) -> str:
    """A valid document with a number replaced by raw text JSON may or may not allow."""
    doc = draw(VALID)
    text = json.dumps(doc)
    numbers = [
        tok for tok in text.replace(",", " ").replace("}", " ").split() if tok[0] in "-0123456789"
    ]
    if not numbers:
        return text
    return text.replace(draw(st.sampled_from(numbers)), draw(NUMBER_TEXT), 1)


@st.composite
def file_bytes(draw: st.DrawFn) -> bytes:
    """Bytes of a would-be JSON file: random structure, mutated valid files, raw numbers,
    deep nesting, big strings, binary data and invalid UTF-8."""
    kind = draw(st.sampled_from(["value", "mutated", "number", "deep", "big", "binary", "bytes"]))
    if kind == "value":
        text = json.dumps(draw(VALUE))
    elif kind == "mutated":
        text = draw(mutated())
    elif kind == "number":
        text = draw(with_raw_number())
    elif kind == "deep":
        n = draw(st.integers(1, 200_000))
        open_, close = draw(st.sampled_from([("[", "]"), ('{"a":', "}"), ('{"model":[', "]}")]))
        text = open_ * n + close * draw(st.integers(0, n))
    elif kind == "big":
        size = draw(st.sampled_from([100, 70_000, 900_000, MAX_BYTES + 1, 3 * MAX_BYTES]))
        char = draw(st.sampled_from(["a", "\\n", "é", '\\"', "[", "7"]))
        doc = json.loads(json.dumps(draw(VALID)))
        doc[draw(st.sampled_from(["model", "format", "note", "force", "Mp"]))] = char * size
        text = json.dumps(doc, ensure_ascii=False).replace("\\\\", "\\")
    else:
        raw = draw(st.binary(max_size=200))
        if kind == "binary":
            return draw(st.sampled_from([b"", b"\x89HDF\r\n\x1a\n"])) + raw
        base = json.dumps(draw(VALID)).encode()
        cut = draw(st.integers(0, len(base)))
        return base[:cut] + raw + base[cut:]
    return text.encode("utf-8", "surrogatepass")


COUNT = {"files": 0, "valid": 0, "refused": 0}


def _read_or_refuse(tmp_path_factory: pytest.TempPathFactory, content: bytes) -> None:
    path = _write(tmp_path_factory.mktemp("gen"), content)
    for what, reader in READERS.items():
        COUNT["files"] += 1
        try:
            value = reader(path)
        except InputError as exc:
            COUNT["refused"] += 1
            _one_line(str(exc), path)
            continue
        COUNT["valid"] += 1
        if what == "parameter":
            try:  # a tissue that reads is one the check can judge
                check(value)
            except InputError as exc:
                _one_line(str(exc), path)


# 150 fixed examples: about 20 of each of the seven kinds of file, each read by every
# reader; the slow run draws 1000 new ones each time
@settings(
    max_examples=150,
    deadline=None,
    derandomize=True,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)
@given(file_bytes())
def test_generated_files_are_read_or_refused_in_one_line(tmp_path_factory, content):
    _read_or_refuse(tmp_path_factory, content)


@pytest.mark.slow
@settings(
    max_examples=1000,
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)
@given(file_bytes())
def test_many_generated_files_are_read_or_refused_in_one_line(tmp_path_factory, content):
    _read_or_refuse(tmp_path_factory, content)


# --------------------------------------------------------------------------- commands


def _cli_paths(path: Path, tmp: Path) -> dict[str, list[str]]:
    params = _write(tmp, VALID_PARAMS, "valid.json")
    return {
        "play --check": ["play", str(path), "--check"],
        "play --profile": ["play", str(params), "--check", "--profile", str(path)],
        "simulate forceps --params": [
            "simulate", "forceps", "--params", str(path), "--duration", "0.05",
            "--link", str(tmp / "forceps"),
        ],
        "record --calibration": [
            "record", "--port", str(tmp / "no-such-port"), "--out", str(tmp / "rec.h5"),
            "--session", "s", "--duration", "0.1", "--calibration", str(path),
        ],
    }  # fmt: skip


CLI_COUNT = {"runs": 0, "exit 0": 0, "exit 1": 0, "tracebacks": 0}


@settings(
    max_examples=60,
    deadline=None,
    derandomize=True,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)
@given(file_bytes())
def test_commands_reading_generated_files_fail_in_one_line(tmp_path_factory, content):
    tmp = tmp_path_factory.mktemp("cli")
    path = _write(tmp, content)
    for name, args in _cli_paths(path, tmp).items():
        result = CliRunner().invoke(cli, args)
        CLI_COUNT["runs"] += 1
        CLI_COUNT["tracebacks"] += "Traceback" in result.output
        assert result.exception is None or isinstance(result.exception, SystemExit), (
            name,
            repr(result.exception),
        )
        assert "Traceback" not in result.output
        CLI_COUNT[f"exit {result.exit_code}"] = CLI_COUNT.get(f"exit {result.exit_code}", 0) + 1
        if result.exit_code == 0:
            assert name in ("play --check", "play --profile", "simulate forceps --params"), name
            continue
        assert result.exit_code == 1, (name, result.output[-500:])
        last = result.output.strip().splitlines()[-1]
        assert last.startswith("Error: "), (name, result.output[-500:])
        _one_line(last, path)


def test_generated_inputs_were_many_and_varied():
    """Runs after the two property tests (file order): they were not vacuous."""
    print(f"\nreaders: {COUNT}; commands: {CLI_COUNT}")
    if COUNT["files"]:
        assert COUNT["refused"] > 0.5 * COUNT["files"]
        assert COUNT["valid"] > 0
    if CLI_COUNT["runs"]:
        assert CLI_COUNT["tracebacks"] == 0


REPRODUCED = [
    ("hdf5", None, "is an HDF5 file, not JSON"),
    ("bad_utf8", b'{"model": "\xff\xfe"}', "not UTF-8"),
    ("deep", "[" * 100_000 + "]" * 100_000, "deep"),
    ("digits", json.dumps(_params()).replace("350.0", "9" * 400), "400-digit integer"),
    ("k1e300", _params(parameters__K__mean=1e300), "<= 1e+06 N/m"),
    ("bigstr", _params(model__f0="a" * 10_000_000), "larger than 1 MiB"),
    ("halfmb", _params(model__f0="a" * 500_000), "is not a stiffness form"),
    ("v99", _params(version=FORMAT_VERSION + 98), "written by a newer tissuecli"),
]


@pytest.mark.parametrize(("name", "content", "needle"), REPRODUCED, ids=[r[0] for r in REPRODUCED])
def test_reproduced_failures_are_one_line_from_the_real_commands(tmp_path, name, content, needle):
    if content is None:
        path = tmp_path / "grasp.h5"
        path.write_bytes(b"\x89HDF\r\n\x1a\n" + bytes(range(256)) * 4)
    else:
        path = _write(tmp_path, content)
    # the first in a process of its own, as a user runs it; the second, which reads the
    # file through the same reader, in this one (an interpreter's start saved)
    for run, args in (
        (tissuecli, ["play", str(path), "--check"]),
        (tissuecli_here, ["simulate", "forceps", "--params", str(path), "--duration", "0.2"]),
    ):
        result = run(*args)
        assert_clean_error(result, needle)
        assert max(len(line) for line in result.stderr.splitlines()) < len(str(path)) + 300


def test_play_check_judges_any_tissue_a_file_may_hold(tmp_path):
    """The largest values a file may hold still get a verdict, not an exception."""
    for f0 in ("x", "x^3"):
        for f1 in ("xdot", "xdot^2"):
            model = Law.paper(f0, f1)
            top = [parameter_range(t) for t in model.terms]
            for values in (top, [top[0], 0.0, 0.0], [0.0, 0.0, 0.0], [1e-300, 1e-300, 1e-300]):
                result = check(Tissue(model, *values))
                assert not result.renderable
                assert all(v is None or math.isfinite(v) for v in _floats(result.as_dict()))


def _floats(value: Any) -> list[Any]:
    if isinstance(value, dict):
        return [x for v in value.values() for x in _floats(v)]
    return [value] if isinstance(value, float) or value is None else []


def test_a_refused_tissue_is_one_line_from_play_check(tmp_path):
    path = _write(tmp_path, _params(parameters__K__mean=5000.0))
    result = CliRunner().invoke(cli, ["play", str(path), "--check"])
    assert result.exit_code == 1 and "Error: the display cannot render" in result.output
