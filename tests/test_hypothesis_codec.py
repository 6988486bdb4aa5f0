"""Properties of the frame codec over every message of the train DBC.

In range: decode(encode(v)) is within half an LSB of v and nothing is counted. Out of range (or +-inf): the
value saturates to the signal's limit, never wraps to the other end, and each saturation is counted once.
Any bytes of the right length decode to values inside the limits; the wrong length is a ValueError naming the
message; the E2E header (counter, CRC) survives the round trip.
"""
from __future__ import annotations

import math

import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from ecu_sim.codec import TrainDb

DB = TrainDb.load()
CODECS = sorted(DB.by_name.values(), key=lambda c: c.frame_id)
SETTINGS = settings(max_examples=200, deadline=None, database=None)


def lsb(codec, i: int) -> float:
    return codec.scales[i]


@st.composite
def in_range(draw):
    codec = draw(st.sampled_from(CODECS))
    values = [draw(st.floats(lo, hi)) for lo, hi in codec.limits]
    return codec, values


@SETTINGS
@given(in_range(), st.integers(0, 15))
def test_round_trip_within_half_an_lsb_and_nothing_counted(case, counter):
    codec, values = case
    before = dict(codec.saturations)
    frame = codec.encode(values, counter)
    assert len(frame) == codec.dlc
    decoded = codec.decode(frame)
    for i, (v, d) in enumerate(zip(values, decoded)):
        assert abs(v - d) <= lsb(codec, i) / 2 * (1 + 1e-9) + 1e-12, (codec.name, codec.signals[i], v, d)
    assert codec.saturations == before
    assert codec.counter_of(frame) == counter and codec.crc_ok(frame)


@st.composite
def beyond_range(draw):
    codec = draw(st.sampled_from(CODECS))
    i = draw(st.integers(0, len(codec.signals) - 1))
    lo, hi = codec.limits[i]
    span = hi - lo
    above = draw(st.booleans())
    margin = draw(st.floats(lsb(codec, i), 1e12 * max(span, 1.0)) | st.just(math.inf))
    values = [(a + b) / 2 for a, b in codec.limits]
    values[i] = hi + margin if above else lo - margin
    return codec, i, values, above


@SETTINGS
@given(beyond_range())
def test_out_of_range_saturates_at_the_near_limit_counted_never_wrapped(case):
    codec, i, values, above = case
    name = codec.signals[i]
    before = codec.saturations[name]
    decoded = codec.decode(codec.encode(values, 0))
    lo, hi = codec.limits[i]
    assert decoded[i] == pytest.approx(hi if above else lo, abs=lsb(codec, i) * 1e-6)
    assert codec.saturations[name] == before + 1
    for j, (v, d) in enumerate(zip(values, decoded)):  # the other signals are untouched
        if j != i:
            assert abs(v - d) <= lsb(codec, j) / 2 * (1 + 1e-9)


@SETTINGS
@given(st.sampled_from(CODECS), st.data())
def test_any_bytes_of_the_right_length_decode_inside_the_limits(codec, data):
    frame = data.draw(st.binary(min_size=codec.dlc, max_size=codec.dlc))
    values = codec.decode(frame)
    for v, (_, _, length, signed, scale, offset, _, _) in zip(values, codec.specs):
        # the bit range can exceed a DBC min/max narrowing: then the value is outside the limits but still a
        # value of the signal's bits, never NaN or inf
        assert math.isfinite(v)
        bits_lo = -(1 << (length - 1)) if signed else 0
        bits_hi = (1 << (length - 1)) - 1 if signed else (1 << length) - 1
        assert bits_lo * scale + offset - 1e-9 <= v <= bits_hi * scale + offset + 1e-9


@SETTINGS
@given(st.sampled_from(CODECS), st.binary(max_size=16))
def test_the_wrong_length_is_a_value_error_naming_the_message(codec, frame):
    assume(len(frame) != codec.dlc)
    with pytest.raises(ValueError, match=codec.name):
        codec.decode(frame)
    with pytest.raises(ValueError, match=codec.name):
        codec.crc_ok(frame)


@SETTINGS
@given(in_range(), st.integers(0, 15), st.integers(0, 63))
def test_a_single_bit_flip_fails_the_crc(case, counter, bit):
    codec, values = case
    frame = bytearray(codec.encode(values, counter))
    assume(bit < 8 * codec.dlc)
    frame[bit // 8] ^= 1 << (bit % 8)
    assert not codec.crc_ok(bytes(frame))


@SETTINGS
@given(st.sampled_from(CODECS), st.integers(0, 15))
def test_nan_is_refused_naming_message_and_signal(codec, counter):
    values = [(a + b) / 2 for a, b in codec.limits]
    values[-1] = math.nan
    with pytest.raises(ValueError, match=f"{codec.name}.{codec.signals[-1]}: cannot encode NaN"):
        codec.encode(values, counter)
