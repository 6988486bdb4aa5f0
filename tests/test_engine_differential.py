"""The compiled frame engine against the Python implementations it replaced: the same bytes, bits and schedules."""
from __future__ import annotations

import math
import random

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import trainhil_engine as engine
from ecu_sim.codec import TrainDb
from ecu_sim.e2e import e2e_crc as python_e2e_crc
from hil.can.frame import frame_bits_reference
from tests.oracle.python_codec import oracle_codec

DB = TrainDb.load()
CODECS = list(DB.by_name.values())
ORACLES = {c.name: oracle_codec(c) for c in CODECS}


def test_every_dbc_message_encodes_to_the_same_bytes_as_the_python_codec():
    rng = random.Random(5)
    for codec in CODECS:
        oracle = ORACLES[codec.name]
        for _ in range(300):
            values = []
            for lo, hi in codec.limits:
                span = hi - lo
                values.append(rng.choice([rng.uniform(lo, hi), rng.uniform(lo - span, hi + span), lo, hi,
                                          round(rng.uniform(lo, hi) / codec.scales[len(values)]) * codec.scales[len(values)]]))
            counter = rng.randrange(16)
            frame = codec.encode(values, counter)
            assert frame == oracle.encode(values, counter), (codec.name, values)
            assert codec.decode(frame) == oracle.decode(frame)
        assert codec.saturations == oracle.saturations, codec.name
        codec.reset_saturations()


@settings(max_examples=300, deadline=None, database=None)
@given(st.sampled_from(CODECS), st.data())
def test_any_frame_decodes_like_the_python_codec(codec, data):
    frame = data.draw(st.binary(min_size=codec.dlc, max_size=codec.dlc))
    assert codec.decode(frame) == ORACLES[codec.name].decode(frame)
    assert codec.crc_ok(frame) == ORACLES[codec.name].crc_ok(frame)


def test_nan_is_an_error_naming_the_signal_in_both():
    codec = DB.sensor(0)
    with pytest.raises(ValueError, match=r"Sensor_U01\.Speed: cannot encode NaN"):
        codec.encode((1.0, math.nan), 0)
    with pytest.raises(ValueError, match=r"Sensor_U01\.Speed: cannot encode NaN"):
        ORACLES[codec.name].encode((1.0, math.nan), 0)


@settings(max_examples=500, deadline=None, database=None)
@given(st.booleans(), st.data())
def test_frame_length_equals_the_bit_by_bit_reference(extended, data):
    can_id = data.draw(st.integers(0, (1 << 29) - 1 if extended else (1 << 11) - 1))
    payload = data.draw(st.binary(max_size=8))
    assert engine.frame_bits(can_id, payload, extended) == frame_bits_reference(can_id, payload, extended)


@settings(max_examples=300, deadline=None, database=None)
@given(st.integers(0, 255), st.binary(min_size=1, max_size=64))
def test_e2e_crc_equals_the_python_table(data_id, payload):
    assert engine.e2e_crc(data_id, payload) == python_e2e_crc(data_id, payload)
