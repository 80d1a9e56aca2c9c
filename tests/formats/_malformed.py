"""HDF5 session files that are not what they seem, drawn by hypothesis.

Shared by ``tests/formats/test_malformed_files.py`` and ``benchmarks/malformed_files.py``. A
drawn :class:`Spec` is written with plain h5py (never through tissuecli's writer), so
anything HDF5 can hold can turn up: datasets of text, compound records, booleans,
complex numbers, references, single values or two columns; missing datasets, groups or
dangling links where datasets belong; counters stored as text; files cut short at a
random byte or made of random bytes.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import h5py
import numpy as np
from hypothesis import strategies as st

from tissuecli.core.errors import TissueError

#: what a dataset can be instead of one number per sample
DATASET_KINDS = (
    "float64",
    "int32",
    "uint8",
    "float32",
    "bool",
    "text",
    "vlen_text",
    "compound",
    "complex",
    "opaque",
    "array_per_row",
    "vlen_float",
    "reference",
    "scalar",
    "two_columns",
    "null_dataspace",
    "missing",
    "group",
    "dangling_link",
    "external_link",
    "shorter",
    "longer",
    "nan",
    "huge_claim",
)
#: attributes tissuecli reads as numbers, flags or text, and the kinds of value stored
ATTR_KEYS = (
    "complete",
    "rows_committed",
    "frames_lost",
    "frames_bad",
    "schema_version",
    "rate_hz",
    "tissue",
    "start_utc",
    "source",
    "clock_map",
    "device",
)
ATTR_VALUES = (
    "int",
    "negative",
    "huge",
    "float",
    "nan",
    "bool",
    "text",
    "number_text",
    "json_text",
    "bad_json",
    "bytes",
    "array1",
    "array3",
    "text_array",
    "empty",
    "compound",
    "complex",
)
CORRUPTIONS = ("none", "truncate", "random_bytes", "signature_then_random", "empty_file")


@dataclass
class Spec:
    """One malformed file: per-dataset kinds, attribute values, and a corruption."""

    n: int
    name: str
    columns: dict[str, str]
    raw: dict[str, str] | None
    attrs: dict[str, str]
    root: str
    corruption: str
    cut: float
    seed: int
    extra: list[str] = field(default_factory=list)


@st.composite
def specs(draw: st.DrawFn) -> Spec:
    """A malformed (or, now and then, valid) session file."""
    kinds = st.sampled_from(DATASET_KINDS)
    plain = st.sampled_from(("float64", "float64", "float64", "int32"))
    columns = {q: draw(st.one_of(plain, kinds)) for q in ("time", "force", "position")}
    raw = draw(
        st.none()
        | st.fixed_dictionaries(
            {
                k: st.sampled_from(
                    (
                        "valid",
                        "valid",
                        "missing",
                        "float64",
                        "text",
                        "scalar",
                        "three_columns",
                        "one_column",
                        "compound",
                    )
                )
                for k in ("counts", "sequence", "device_clock", "host_time")
            }
        )
    )
    attrs = draw(
        st.dictionaries(st.sampled_from(ATTR_KEYS), st.sampled_from(ATTR_VALUES), max_size=6)
    )
    return Spec(
        # 300 rows now and then: enough for fit to run to the end on the valid ones
        n=draw(st.one_of(st.integers(0, 40), st.just(300))),
        name=draw(st.sampled_from(("liver-1", "a", "séance 2", "x" * 80))),
        columns=columns,
        raw=raw,
        attrs=attrs,
        root=draw(st.sampled_from(("tissuecli", "tissuecli", "none", "foreign"))),
        corruption=draw(st.sampled_from(CORRUPTIONS[:1] * 6 + CORRUPTIONS[1:])),
        cut=draw(st.floats(0.0, 1.0)),
        seed=draw(st.integers(0, 2**16)),
        extra=draw(
            st.lists(
                st.sampled_from(("valid_session", "dataset_in_sessions", "sessions_attr")),
                max_size=2,
                unique=True,
            )
        ),
    )


def _dataset(g: h5py.Group, key: str, kind: str, n: int, base: np.ndarray) -> None:
    """Store `kind` under `key` in `g` (`base`: n valid values)."""
    if kind == "missing":
        return
    if kind == "group":
        g.create_group(key)
        return
    if kind == "dangling_link":
        g[key] = h5py.SoftLink("/nowhere/at/all")
        return
    if kind == "external_link":
        g[key] = h5py.ExternalLink("no-such-file.h5", "/x")
        return
    if kind == "huge_claim":
        ds = g.create_dataset(key, shape=(10**12,), maxshape=(None,), chunks=(4096,), dtype="f8")
        ds.attrs["unit"] = "s"
        return
    data: Any
    if kind in ("float64", "shorter", "longer", "nan"):
        data = np.asarray(base, dtype=np.float64)
        if kind == "shorter":
            data = data[: n // 2]
        elif kind == "longer":
            data = np.concatenate([data, data + 1.0])
        elif kind == "nan":
            data = np.full(n, np.nan)
    elif kind == "int32":
        data = np.arange(n, dtype=np.int32)
    elif kind == "uint8":
        data = (np.arange(n) % 256).astype(np.uint8)
    elif kind == "float32":
        data = base.astype(np.float32)
    elif kind == "bool":
        data = np.ones(n, dtype=bool)
    elif kind == "text":
        data = np.array([b"1.5"] * n, dtype="S8")
    elif kind == "vlen_text":
        data = np.array(["1.5"] * n, dtype=h5py.string_dtype())
    elif kind == "compound":
        data = np.zeros(n, dtype=[("a", "f8"), ("b", "i4")])
    elif kind == "complex":
        data = base.astype(np.complex128)
    elif kind == "opaque":
        data = np.zeros(n, dtype="V4")
    elif kind == "array_per_row":
        g.create_dataset(key, shape=(n,), dtype=np.dtype(("f8", (3,))))
        return
    elif kind == "vlen_float":
        ds = g.create_dataset(key, shape=(n,), dtype=h5py.vlen_dtype(np.float64))
        for i in range(n):
            ds[i] = np.arange(i % 3, dtype=np.float64)
        return
    elif kind == "reference":
        ds = g.create_dataset(key, shape=(n,), dtype=h5py.ref_dtype)
        for i in range(n):
            ds[i] = g.ref
        return
    elif kind == "scalar":
        g.create_dataset(key, data=1.5)
        return
    elif kind == "two_columns":
        data = np.stack([base, base], axis=1)
    elif kind == "null_dataspace":
        g.create_dataset(key, data=h5py.Empty("f8"))
        return
    else:
        raise ValueError(kind)
    g.create_dataset(key, data=data, maxshape=(None, *np.shape(data)[1:]))


def _raw(g: h5py.Group, key: str, kind: str, n: int) -> None:
    i = np.arange(n)
    if kind == "missing":
        return
    values: dict[str, Any] = {
        "counts": np.stack([i, -i], axis=1).astype(np.int16),
        "sequence": i.astype(np.uint32),
        "device_clock": (10 * i).astype(np.int64),
        "host_time": i * 1e-3,
    }
    data = values[key]
    if kind == "float64":
        data = np.asarray(data, dtype=np.float64)
    elif kind == "text":
        data = np.array([b"7"] * n)
    elif kind == "scalar":
        data = np.int64(3)
    elif kind == "three_columns":
        data = np.zeros((n, 3), dtype=np.int16)
    elif kind == "one_column":
        data = np.zeros(n, dtype=np.int16)
    elif kind == "compound":
        data = np.zeros(n, dtype=[("a", "i2"), ("b", "i2")])
    g.create_dataset(f"raw/{key}", data=data)
    if key == "counts" and kind == "valid":
        g["raw/counts"].attrs["conversion"] = np.array([0.01, 1e-6])
        g["raw/counts"].attrs["offset"] = np.array([0.0, 0.0])
        g["raw/counts"].attrs["channels"] = np.array(
            ["force", "position"], dtype=h5py.string_dtype()
        )


def _attr(kind: str, rng: np.random.Generator) -> Any:
    return {
        "int": np.int64(rng.integers(0, 50)),
        "negative": np.int64(-3),
        "huge": np.uint64(2**64 - 1),
        "float": 2.5,
        "nan": float("nan"),
        "bool": True,
        "text": "yes",
        "number_text": "12",
        "json_text": '{"slope": 1.0, "offset": 0.0}',
        "bad_json": '{"slope": ',
        "bytes": np.bytes_(b"\xff\xfe raw"),
        "array1": np.array([7]),
        "array3": np.array([1.0, 2.0, 3.0]),
        "text_array": np.array(["a", "b"], dtype=h5py.string_dtype()),
        "empty": h5py.Empty("f"),
        "compound": np.array((1, 2.0), dtype=[("a", "i4"), ("b", "f8")]),
        "complex": np.complex128(1 + 2j),
    }[kind]


def _samples(n: int, rng: np.random.Generator) -> dict[str, np.ndarray]:
    """n samples of a grasp at 1 kHz: 350 N/m, 3 N s/m, 0.05 kg, a little noise."""
    t = np.arange(n) * 1e-3
    w = 2 * np.pi * 3.0
    x = 2e-3 * (1 - np.cos(w * t))
    force = 350 * x + 3 * 2e-3 * w * np.sin(w * t) + 0.05 * 2e-3 * w * w * np.cos(w * t)
    return {
        "time": t,
        "force": force + rng.normal(0, 0.005, n),
        "position": x + rng.normal(0, 2e-6, n),
    }


def write_spec(path: Path, spec: Spec) -> None:
    """Write the file `spec` describes at `path` (replacing it)."""
    rng = np.random.default_rng(spec.seed)
    n = spec.n
    base = _samples(n, rng)
    with h5py.File(path, "w") as f:
        if spec.root == "tissuecli":
            f.attrs["schema_version"] = 1
            f.attrs["software"] = "tissuecli 0.1.0"
        elif spec.root == "foreign":
            f.attrs["creator"] = "another program"
        g = f.create_group(f"sessions/{spec.name}")
        for key, kind in spec.columns.items():
            _dataset(g, key, kind, n, base[key])
        if spec.raw is not None:
            for key, kind in spec.raw.items():
                _raw(g, key, kind, n)
        g.attrs["complete"] = True
        g.attrs["rows_committed"] = np.int64(n)
        for key, kind in spec.attrs.items():
            g.attrs[key] = _attr(kind, rng)
        if "valid_session" in spec.extra:
            v = f.create_group("sessions/valid")
            for key in ("time", "force", "position"):
                v.create_dataset(key, data=base[key])
            v.attrs["complete"] = True
        if "dataset_in_sessions" in spec.extra:
            f.create_dataset("sessions/not-a-session", data=np.arange(3))
        if "sessions_attr" in spec.extra:
            f["sessions"].attrs["note"] = "x"
    corrupt(path, spec.corruption, spec.cut, spec.seed)


def corrupt(path: Path, how: str, cut: float, seed: int) -> None:
    """Cut the file at a fraction `cut` of its length, or replace it with random bytes."""
    rng = np.random.default_rng(seed)
    size = path.stat().st_size
    if how == "truncate":
        os.truncate(path, int(cut * size))
    elif how == "random_bytes":
        path.write_bytes(rng.integers(0, 256, int(cut * 4096), dtype=np.uint8).tobytes())
    elif how == "signature_then_random":
        path.write_bytes(
            b"\x89HDF\r\n\x1a\n" + rng.integers(0, 256, 96 + int(cut * 4096), np.uint8).tobytes()
        )
    elif how == "empty_file":
        path.write_bytes(b"")


def clean(call: Any) -> str:
    """Run `call`; 'ok' if it returns, 'error' for a one-line TissueError.

    Anything else (a traceback) propagates; so does a message with a newline.
    """
    try:
        call()
    except TissueError as exc:
        message = str(exc)
        assert message and "\n" not in message, repr(message)
        assert len(message) < 600, message
        return "error"
    return "ok"
