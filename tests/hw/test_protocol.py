"""Tests of the wire protocol: CRC, COBS, messages, the stream decoder and sequence numbers.

Every property runs derandomized, so the suite is deterministic.
"""

from __future__ import annotations

import itertools
import struct

import numpy as np
import pytest
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

from tissuecli.core.calibration import Channel
from tissuecli.hw.protocol import (
    COMMANDS,
    FLAG_LIMIT,
    FLAG_MODEL,
    FLAG_STALE,
    FLAG_WATCHDOG,
    IDENTIFY,
    MAX_FRAME,
    MESSAGES,
    START,
    STOP,
    Command,
    Encoder,
    FrameDecoder,
    Info,
    Message,
    Sample,
    SequenceTracker,
    SetModel,
    SetVoltage,
    cobs_decode,
    cobs_encode,
    crc16,
    decode_frame,
    encode,
)

MASK32 = 0xFFFFFFFF


def fixed(max_examples: int = 100) -> settings:
    return settings(
        derandomize=True,
        max_examples=max_examples,
        deadline=None,
        suppress_health_check=[HealthCheck.too_slow, HealthCheck.filter_too_much],
    )


u8 = st.integers(0, 0xFF)
u32 = st.integers(0, MASK32)
i16 = st.integers(-(1 << 15), (1 << 15) - 1)
i32 = st.integers(-(1 << 31), (1 << 31) - 1)
f32 = st.floats(width=32, allow_nan=False)  # every value is exactly representable in float32

json_values = st.recursive(
    st.none()
    | st.booleans()
    | st.integers(-(1 << 53), 1 << 53)
    | st.floats(allow_nan=False, allow_infinity=False)
    | st.text(max_size=6),
    lambda inner: (
        st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=6), inner, max_size=4)
    ),
    max_leaves=8,  # keeps every Info frame under MAX_FRAME
)

MESSAGE_STRATEGIES: dict[type[Message], st.SearchStrategy[Message]] = {
    Sample: st.builds(Sample, u32, u32, i16, i16),
    Encoder: st.builds(Encoder, u32, u32, i32, f32, u8),
    SetVoltage: st.builds(SetVoltage, u32, f32),
    SetModel: st.builds(SetModel, u32, f32, f32, f32, f32),
    Command: st.builds(Command, u8),
    Info: st.builds(Info, st.dictionaries(st.text(max_size=6), json_values, max_size=4)),
}
# messages whose frames stay well below MAX_FRAME
short_messages = st.one_of(
    *(MESSAGE_STRATEGIES[k] for k in (Sample, Encoder, SetVoltage, SetModel, Command)),
    st.builds(Info, st.dictionaries(st.text("abc", max_size=5), st.integers(), max_size=4)),
)
samples = MESSAGE_STRATEGIES[Sample]


def crc16_reference(data: bytes) -> int:
    """CRC-16/CCITT-FALSE bit by bit, straight from its parameters."""
    crc = 0xFFFF
    for byte in data:
        crc ^= byte << 8
        for _ in range(8):
            crc = ((crc << 1) ^ 0x1021) if crc & 0x8000 else (crc << 1)
            crc &= 0xFFFF
    return crc


def decodes(piece: bytes) -> bool:
    """Whether ``piece`` (a frame without its delimiter) is accepted as a message."""
    try:
        decode_frame(piece)
    except ValueError:
        return False
    return True


def code_positions(encoded: bytes) -> set[int]:
    """Indices of the COBS code bytes in a valid encoding (all others are data bytes)."""
    positions, i = set(), 0
    while i < len(encoded):
        positions.add(i)
        i += encoded[i]
    return positions


def feed_in_chunks(decoder: FrameDecoder, data: bytes, sizes: list[int]) -> list[Message]:
    out: list[Message] = []
    pos = 0
    for size in itertools.cycle(sizes):
        if pos >= len(data):
            break
        out += decoder.feed(data[pos : pos + size])
        pos += size
    return out


# --------------------------------------------------------------------------- CRC


def test_crc16_check_value() -> None:
    assert crc16(b"123456789") == 0x29B1
    assert crc16(b"") == 0xFFFF  # init, no final xor


@fixed(200)
@given(st.binary(max_size=300))
def test_crc16_matches_bitwise_reference(data: bytes) -> None:
    assert crc16(data) == crc16_reference(data)


@fixed(200)
@given(st.binary(min_size=1, max_size=64), st.data())
def test_crc16_detects_every_single_bit_error(data: bytes, draw: st.DataObject) -> None:
    bit = draw.draw(st.integers(0, 8 * len(data) - 1))
    corrupted = bytearray(data)
    corrupted[bit // 8] ^= 1 << (bit % 8)
    assert crc16(bytes(corrupted)) != crc16(data)


# --------------------------------------------------------------------------- COBS

nonzero_run = st.integers(1, 600).flatmap(
    lambda n: st.binary(min_size=n, max_size=n).map(lambda b: b.replace(b"\x00", b"\x07"))
)
edge_run = st.sampled_from([253, 254, 255, 508, 509]).map(lambda n: bytes([0xA5]) * n)
zero_run = st.integers(1, 300).map(lambda n: b"\x00" * n)
cobs_inputs = st.binary(max_size=600) | st.lists(
    nonzero_run | edge_run | zero_run | st.binary(max_size=20), max_size=6
).map(b"".join)


@pytest.mark.parametrize(
    "data",
    [
        b"",
        b"\x00",
        b"\x00" * 600,
        b"\x11" * 253,
        b"\x11" * 254,
        b"\x11" * 255,
        b"\x11" * 508,
        b"\x11" * 254 + b"\x00",
        b"\x00" + b"\x11" * 254 + b"\x00" + b"\x22" * 255,
        bytes(range(256)) * 3,
    ],
)
def test_cobs_round_trip_edges(data: bytes) -> None:
    encoded = cobs_encode(data)
    assert b"\x00" not in encoded
    assert cobs_decode(encoded) == data


@fixed(300)
@given(cobs_inputs)
def test_cobs_round_trip(data: bytes) -> None:
    encoded = cobs_encode(data)
    assert b"\x00" not in encoded
    # overhead: one code byte per zero-delimited block plus one per 254-byte run
    assert len(encoded) <= len(data) + 1 + len(data) // 254
    assert cobs_decode(encoded) == data


@pytest.mark.parametrize(
    "data",
    [b"\x00", b"\x02\x00", b"\x03a\x00", b"\x05ab", b"\xff" + b"\x11" * 10, b"\x02a\x03b"],
)
def test_cobs_decode_rejects_invalid(data: bytes) -> None:
    with pytest.raises(ValueError):
        cobs_decode(data)


@fixed(300)
@given(st.binary(max_size=300))
def test_cobs_decode_only_raises_value_error(data: bytes) -> None:
    try:
        cobs_decode(data)
    except ValueError:
        return
    # whatever decodes contained no zero byte: every byte is a code or a data byte
    assert b"\x00" not in data


#: any bytes (at most 300) holding a zero: a zero put into any string at any place, drawn
#: directly rather than filtered out of plain strings (most of which have none)
with_a_zero = st.tuples(st.binary(max_size=299), st.integers(0, 299)).map(
    lambda d: d[0][: d[1]] + b"\x00" + d[0][d[1] :]
)


@fixed(100)
@given(with_a_zero)
def test_cobs_decode_rejects_any_zero_byte(data: bytes) -> None:
    with pytest.raises(ValueError):
        cobs_decode(data)


# --------------------------------------------------------------------------- messages


def test_every_message_type_is_covered() -> None:
    assert set(MESSAGE_STRATEGIES) == set(MESSAGES.values())
    assert {m.TYPE for m in MESSAGE_STRATEGIES} == set(MESSAGES)
    assert len(MESSAGES) == 6  # types are distinct


def test_type_bytes_and_constants() -> None:
    assert (
        Sample.TYPE,
        Encoder.TYPE,
        Info.TYPE,
        Command.TYPE,
        SetVoltage.TYPE,
        SetModel.TYPE,
    ) == (0x01, 0x02, 0x03, 0x10, 0x21, 0x22)
    assert (IDENTIFY, START, STOP) == (1, 2, 3)
    assert COMMANDS == {"identify": IDENTIFY, "start": START, "stop": STOP}
    assert (FLAG_WATCHDOG, FLAG_LIMIT, FLAG_STALE, FLAG_MODEL) == (0x01, 0x02, 0x04, 0x08)


@pytest.mark.parametrize("kind", list(MESSAGE_STRATEGIES), ids=lambda k: k.__name__)
@fixed(150)
@given(draw=st.data())
def test_encode_decode_round_trip(kind: type[Message], draw: st.DataObject) -> None:
    message = draw.draw(MESSAGE_STRATEGIES[kind])
    frame = encode(message)
    assert frame.endswith(b"\x00") and b"\x00" not in frame[:-1]
    decoded = decode_frame(frame[:-1])
    assert type(decoded) is kind
    assert decoded == message
    assert decoded.pack() == message.pack()  # bit for bit, -0.0 included
    decoder = FrameDecoder()
    assert decoder.feed(frame) == [message]
    assert (decoder.good_frames, decoder.bad_frames) == (1, 0)


@pytest.mark.parametrize(
    ("kind", "frame_len"),
    [(Sample, 17), (Encoder, 22), (SetVoltage, 13), (SetModel, 25), (Command, 6)],
)
@fixed(50)
@given(draw=st.data())
def test_fixed_frame_sizes(kind: type[Message], frame_len: int, draw: st.DataObject) -> None:
    message = draw.draw(MESSAGE_STRATEGIES[kind])
    assert len(message.pack()) == 1 + struct.calcsize("<" + kind.FORMAT)
    # payload + 2 CRC bytes + 1 COBS code byte + 1 delimiter, whatever the values
    assert len(encode(message)) == len(message.pack()) + 4 == frame_len


def test_sample_wire_layout() -> None:
    """The worked example of docs/protocol.md, byte for byte."""
    message = Sample(seq=1, clock=1000, force=-3, position=120)
    assert message.pack() == bytes.fromhex("01 01000000 e8030000 fdff 7800")
    assert crc16(message.pack()) == 0x3023
    assert encode(message) == bytes.fromhex("03 01 01 01 01 03 e8 03 01 04 fd ff 78 03 30 23 00")


def test_encoder_and_set_voltage_layout() -> None:
    enc = Encoder(seq=7, clock=2, position=-5, volts=1.5, flags=FLAG_WATCHDOG | FLAG_LIMIT)
    assert enc.pack() == bytes.fromhex("02 07000000 02000000 fbffffff 0000c03f 03")
    assert SetVoltage(seq=9, volts=-2.0).pack() == bytes.fromhex("21 09000000 000000c0")
    assert SetModel(seq=9, volts=1.0, u=1.0, du_dx=-2.0, du_dv=0.5).pack() == bytes.fromhex(
        "22 09000000 0000803f 0000803f 000000c0 0000003f"
    )
    assert Command(START).pack() == b"\x10\x02"
    assert Info({"protocol": 1}).pack() == b'\x03{"protocol":1}'


@pytest.mark.parametrize(
    ("message", "frame"),
    [
        (Command(IDENTIFY), "05 10 01 0e 5d 00"),
        (Command(START), "05 10 02 3e 3e 00"),
        (Command(STOP), "05 10 03 2e 1f 00"),
        (SetVoltage(seq=7, volts=2.5), "03 21 07 01 01 01 01 05 20 40 dd 97 00"),
        (
            Encoder(seq=42, clock=123456, position=-200, volts=2.5, flags=FLAG_WATCHDOG),
            "03 02 2a 01 01 04 40 e2 01 05 38 ff ff ff 01 06 20 40 01 91 5b 00",
        ),
    ],
)
def test_documented_test_vectors(message: Message, frame: str) -> None:
    assert encode(message) == bytes.fromhex(frame)
    assert decode_frame(bytes.fromhex(frame)[:-1]) == message


def _framed(payload: bytes) -> bytes:
    """A frame with a valid CRC around any payload (without delimiter)."""
    return cobs_encode(payload + crc16(payload).to_bytes(2, "big"))


@pytest.mark.parametrize(
    "payload",
    [
        b"\x01",  # Sample without body
        b"\x01" + b"\x00" * 11,  # Sample one byte short
        b"\x01" + b"\x00" * 13,  # Sample one byte long
        b"\x7f" + b"\x00" * 12,  # unknown type
        b"\x03[1, 2]",  # Info that is not an object
        b"\x03{",  # Info that is not JSON
        b"\x03\xff\xfe",  # Info that is not UTF-8
        b"\x03",  # empty Info
        b"\x10",  # Command without code
    ],
)
def test_decode_frame_rejects_bad_payloads(payload: bytes) -> None:
    with pytest.raises(ValueError):
        decode_frame(_framed(payload))


def test_decode_frame_rejects_bad_crc_and_short_frames() -> None:
    good = encode(Sample(1, 2, 3, 4))[:-1]
    bad = bytearray(good)
    bad[-1] ^= 0x01
    assert crc16(b"") == 0xFFFF  # so b"\x03\xff\xff" is an empty payload with a valid CRC
    short = (b"\x01", b"\x02\x01", b"\x03\x01\x01", b"\x01\x01\x01", b"\x03\xff\xff")
    for frame in (bytes(bad), *short):
        with pytest.raises(ValueError):
            decode_frame(frame)


@fixed(300)
@given(st.sampled_from([*MESSAGES, 0x00, 0x7F, 0xFF]), st.binary(max_size=40))
def test_decode_frame_only_raises_value_error(kind: int, body: bytes) -> None:
    """CRC-valid frames with arbitrary bodies: a message of that type, or ValueError."""
    payload = bytes([kind]) + body
    for frame in (_framed(payload), cobs_encode(payload), payload.replace(b"\x00", b"\x01")):
        try:
            message = decode_frame(frame)
        except ValueError:
            continue
        assert message.TYPE == kind


# --------------------------------------------------------------------------- stream decoder


@st.composite
def noisy_streams(draw: st.DrawFn) -> tuple[bytes, list[tuple[int, Message]], int, list[int]]:
    """Sample frames on a bad line.

    Before a frame there may be line noise ending in a delimiter (noise that does
    not happen to be a valid frame); each frame is then either intact, has one bit
    flipped in a COBS data byte (its decoded body differs in exactly one bit, which
    CRC-16 always detects), is cut short before its delimiter (a shorter Sample
    body is always rejected by its length), or is preceded by non-zero garbage
    without a delimiter, which merges with it into one bad frame.

    Returns the stream, ``(end offset, message)`` of every intact frame, the exact
    number of bad frames a decoder must count, and chunk sizes to feed it in.
    """
    n = draw(st.integers(1, 12))
    first = draw(u32)
    stream = bytearray()
    expected: list[tuple[int, Message]] = []
    bad = 0
    noise_st = st.binary(max_size=24).filter(
        lambda g: not any(decodes(p) for p in g.split(b"\x00") if p)
    )
    for i in range(n):
        message = Sample((first + i) & MASK32, draw(u32), draw(i16), draw(i16))
        body = encode(message)[:-1]
        if draw(st.booleans()):
            noise = draw(noise_st)
            stream += noise + b"\x00"
            bad += sum(1 for p in noise.split(b"\x00") if p)
        fate = draw(st.sampled_from(["intact", "intact", "flip", "truncate", "merge"]))
        if fate == "flip":
            data_bytes = sorted(set(range(len(body))) - code_positions(body))
            i_byte = draw(st.sampled_from(data_bytes))
            bit = draw(st.integers(0, 7))
            if body[i_byte] ^ (1 << bit) == 0:  # keep the zero-free body: pick another bit
                bit = (bit + 1) % 8
            flipped = bytearray(body)
            flipped[i_byte] ^= 1 << bit
            body = bytes(flipped)
        elif fate == "truncate":
            body = body[: draw(st.integers(1, len(body) - 1))]
        elif fate == "merge":
            garbage = draw(st.binary(min_size=1, max_size=16)).replace(b"\x00", b"\x5a")
            assume(not decodes(garbage + body))
            body = garbage + body
        stream += body + b"\x00"
        if fate == "intact":
            expected.append((len(stream), message))
        else:
            bad += 1
    if draw(st.booleans()):  # the line goes quiet in the middle of a frame
        tail = encode(Sample((first + n) & MASK32, 0, 0, 0))[:-1]
        stream += tail[: draw(st.integers(1, len(tail)))]
    sizes = draw(st.lists(st.integers(1, 40), min_size=1, max_size=8))
    return bytes(stream), expected, bad, sizes


@fixed(400)
@given(noisy_streams())
def test_decoder_recovers_from_line_faults(
    case: tuple[bytes, list[tuple[int, Message]], int, list[int]],
) -> None:
    stream, expected, bad, sizes = case
    decoder = FrameDecoder()
    out: list[Message] = []
    pos = 0
    for size in itertools.cycle(sizes):
        if pos >= len(stream):
            break
        out += decoder.feed(stream[pos : pos + size])  # (a) never raises
        pos = min(pos + size, len(stream))
        # recovery is immediate: every intact frame is out as soon as its delimiter is in
        assert out == [m for end, m in expected if end <= pos]
    # (b) every intact frame, in order, exactly once; (c) nothing that was not sent
    assert out == [m for _, m in expected]
    assert decoder.good_frames == len(expected)
    # (d) every corrupted, truncated or merged frame and every noise burst counted once
    assert decoder.bad_frames == bad


@fixed(300)
@given(
    st.lists(
        short_messages.map(encode) | st.binary(max_size=40) | st.just(b"\x00"),
        max_size=20,
    ).map(b"".join),
    st.lists(st.integers(1, 64), min_size=1, max_size=8),
)
def test_chunking_does_not_matter(stream: bytes, sizes: list[int]) -> None:
    """Byte by byte, all at once or in any chunks: same messages, same counters."""
    results = []
    for chunking in ([len(stream) or 1], [1], sizes):
        decoder = FrameDecoder()
        out = feed_in_chunks(decoder, stream, chunking)
        results.append((out, decoder.good_frames, decoder.bad_frames))
    assert results[0] == results[1] == results[2]


def test_idle_delimiters_are_not_errors() -> None:
    decoder = FrameDecoder()
    frame = encode(Sample(5, 6, 7, 8))
    assert decoder.feed(b"\x00\x00" + frame + b"\x00\x00\x00" + frame) == [Sample(5, 6, 7, 8)] * 2
    assert (decoder.good_frames, decoder.bad_frames) == (2, 0)


def test_partial_frame_waits_for_its_delimiter() -> None:
    decoder = FrameDecoder()
    frame = encode(Sample(5, 6, 7, 8))
    assert decoder.feed(frame[:-1]) == []
    assert decoder.feed(b"") == []
    assert decoder.feed(frame[-1:] + frame[:3]) == [Sample(5, 6, 7, 8)]
    assert decoder.feed(frame[3:]) == [Sample(5, 6, 7, 8)]
    assert (decoder.good_frames, decoder.bad_frames) == (2, 0)


@pytest.mark.parametrize("length", [MAX_FRAME + 1, MAX_FRAME + 2, 2 * MAX_FRAME + 7, 10_000])
@pytest.mark.parametrize("chunk", [1, 7, 64, 100_000])
def test_overlong_garbage_is_dropped_and_next_frame_decodes(length: int, chunk: int) -> None:
    rng = np.random.default_rng(length + chunk)
    garbage = rng.integers(1, 256, length, dtype=np.uint8).tobytes()
    f1, f2 = Sample(1, 1000, -3, 120), Sample(2, 2000, -4, 121)
    decoder = FrameDecoder()
    assert feed_in_chunks(decoder, garbage, [chunk]) == []
    assert decoder.bad_frames >= 1  # dropped and counted before any delimiter arrives
    out = feed_in_chunks(decoder, b"\x00" + encode(f1) + encode(f2), [chunk])
    assert out == [f1, f2]
    assert decoder.good_frames == 2


@pytest.mark.parametrize("length", [MAX_FRAME + 1, 2 * MAX_FRAME + 2, 2 * (MAX_FRAME + 1), 5000])
@pytest.mark.parametrize("chunk", [1, 13, 100_000])
def test_undelimited_overlong_garbage_loses_one_frame_at_most(length: int, chunk: int) -> None:
    rng = np.random.default_rng(length * chunk)
    garbage = rng.integers(1, 256, length, dtype=np.uint8).tobytes()
    f1, f2 = Sample(1, 1000, -3, 120), Sample(2, 2000, -4, 121)
    decoder = FrameDecoder()
    out = feed_in_chunks(decoder, garbage + encode(f1) + encode(f2), [chunk])
    assert out in ([f2], [f1, f2])
    assert decoder.bad_frames >= 1


def test_deeply_nested_info_is_a_bad_frame_not_a_crash() -> None:
    payload = b"\x03" + b"[" * 1000  # CRC-valid, 1007-byte frame, within MAX_FRAME
    frame = _framed(payload)
    assert len(frame) <= MAX_FRAME
    decoder = FrameDecoder()
    assert decoder.feed(frame + b"\x00") == []
    assert decoder.bad_frames == 1


def test_overlong_frames_are_refused_by_encode() -> None:
    with pytest.raises(ValueError, match="exceeds"):
        encode(Info({"k": "x" * 1100}))


def test_overlong_frames_do_not_depend_on_chunking() -> None:
    garbage = b"\x55" * 1500 + b"\x00" + encode(Sample(1, 1000, -3, 120))
    big_info = _framed(b"\x03" + b'"' + b"x" * 1100 + b'"') + b"\x00"
    for stream in (garbage, big_info, garbage * 3 + big_info):
        whole, single = FrameDecoder(), FrameDecoder()
        assert whole.feed(stream) == feed_in_chunks(single, stream, [1])
        assert (whole.good_frames, whole.bad_frames) == (single.good_frames, single.bad_frames)


# --------------------------------------------------------------------------- sequence numbers


def test_sequence_first_and_consecutive() -> None:
    tracker = SequenceTracker()
    assert [tracker.update(s) for s in range(100, 110)] == [0] * 10
    assert (tracker.lost, tracker.restarts, tracker.last) == (0, 0, 109)


def test_sequence_wraps_without_loss() -> None:
    tracker = SequenceTracker()
    assert [tracker.update(s) for s in (0xFFFFFFFE, 0xFFFFFFFF, 0, 1)] == [0, 0, 0, 0]
    assert (tracker.lost, tracker.restarts) == (0, 0)
    assert tracker.update(4) == 2  # 2 and 3 lost
    assert tracker.lost == 2


@fixed(200)
@given(u32, st.lists(st.integers(1, 5000), min_size=1, max_size=50))
def test_sequence_counts_gaps_across_wrap(start: int, steps: list[int]) -> None:
    tracker = SequenceTracker()
    tracker.update(start)
    seq = start
    for step in steps:
        seq = (seq + step) & MASK32
        assert tracker.update(seq) == step - 1
    assert tracker.lost == sum(steps) - len(steps)
    assert tracker.restarts == 0


@fixed(200)
@given(u32, st.integers(1, 1 << 31), st.integers(0, 100))
def test_sequence_backwards_jump_is_a_restart(start: int, back: int, after: int) -> None:
    tracker = SequenceTracker()
    tracker.update(start)
    restart_at = (start - back) & MASK32
    assert tracker.update(restart_at) == 0
    assert (tracker.lost, tracker.restarts) == (0, 1)
    for k in range(1, after + 1):  # counting resumes from the new sequence
        assert tracker.update((restart_at + k) & MASK32) == 0
    assert tracker.update((restart_at + after + 3) & MASK32) == 2
    assert (tracker.lost, tracker.restarts) == (2, 1)


def test_sequence_device_reset_and_huge_jump() -> None:
    tracker = SequenceTracker(max_gap=1000)
    tracker.update(50_000)
    assert tracker.update(0) == 0  # the device restarted
    assert tracker.update(1001) == 0  # more than max_gap ahead: a restart too
    assert tracker.update(2001) == 999  # exactly max_gap ahead: loss
    assert (tracker.lost, tracker.restarts) == (999, 2)
    assert tracker.update(2001) == 0  # a repeat is never loss
    assert tracker.lost == 999


# --------------------------------------------------------------------------- calibration


channels = st.builds(
    lambda lo, span, bits, flip: (
        Channel.spanning(*((lo + span, lo) if flip else (lo, lo + span)), bits, "N"),
        bits,
    ),
    st.floats(-100.0, 100.0),
    st.floats(1e-3, 100.0),
    st.integers(8, 16),
    st.booleans(),
)


@fixed(300)
@given(channels, st.lists(st.floats(0.0, 1.0), min_size=1, max_size=50))
def test_to_counts_round_trip_within_half_a_step(case: tuple[Channel, int], u: list[float]) -> None:
    channel, bits = case
    lo, hi = -(1 << (bits - 1)), (1 << (bits - 1)) - 1
    a, b = channel.to_si([lo, hi])
    values = a + np.asarray(u) * (b - a)  # inside the ADC's range
    counts = channel.to_counts(values, bits)
    assert counts.dtype == np.int16
    assert np.all((counts >= lo) & (counts <= hi))
    err = np.abs(channel.to_si(counts) - values)
    assert np.all(err <= abs(channel.gain) * (0.5 + 1e-6))


@fixed(200)
@given(channels, st.floats(1.0, 1e6))
def test_to_counts_saturates(case: tuple[Channel, int], beyond: float) -> None:
    channel, bits = case
    lo, hi = -(1 << (bits - 1)), (1 << (bits - 1)) - 1
    a, b = channel.to_si([lo, hi])  # SI values at the two ends (b < a for a negative gain)
    span = abs(b - a)
    values = [b + np.sign(b - a) * beyond * span, a - np.sign(b - a) * beyond * span]
    assert channel.to_counts(values, bits).tolist() == [hi, lo]
    assert channel.to_counts([np.inf, -np.inf], bits).tolist() == (
        [hi, lo] if channel.gain > 0 else [lo, hi]
    )


@pytest.mark.parametrize("bits", range(8, 17))
def test_spanning_maps_full_range_onto_adc_ends(bits: int) -> None:
    channel = Channel.spanning(-1.0, 5.0, bits, "N")
    lo, hi = -(1 << (bits - 1)), (1 << (bits - 1)) - 1
    assert channel.to_si([lo, hi]) == pytest.approx([-1.0, 5.0], abs=1e-12)
    assert channel.to_counts([-1.0, 5.0, -2.0, 6.0], bits).tolist() == [lo, hi, lo, hi]
