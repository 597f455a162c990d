"""The wire format: every message type seqvpr sends or reads is declared to DDS with the fields ``rosbags`` knows, and
the bytes (cyclonedds' own encoding of the declaration, what the node sends, what it reads) are ``rosbags``' CDR."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from seqvpr.ros2.messages import (
    COMPRESSED, EMPTY, IMAGE, MESSAGE_TYPES, NAVSATFIX, ODOMETRY, POSE, STATUS, decode, dds_topic, dds_typename, encode,
    message, outgoing, typestore, wire_type,
)
from seqvpr.ros2.dds import Recorder

cyclonedds_idl = pytest.importorskip("cyclonedds.idl")


def sample(msgtype: str, rng: np.random.Generator, size: int = 3):
    """A message of ``msgtype`` with every field filled from ``rng`` (strings, sequences of ``size`` items)."""
    from rosbags.typesys.base import Nodetype

    fields = {}
    for name, node in typestore().fielddefs[msgtype][1]:
        fields[name] = _value(node, rng, size, Nodetype)
    return message(msgtype, **fields)


def _value(node, rng, size, Nodetype):
    kind, spec = node
    if kind == Nodetype.NAME:
        return sample(spec, rng, size)
    if kind == Nodetype.BASE:
        name = spec[0]
        if name == "string":
            return "".join(rng.choice(list("abcxyz/_09"), size=int(rng.integers(0, 12))))
        if name == "bool":
            return bool(rng.integers(0, 2))
        if name.startswith("float"):
            return float(rng.standard_normal())
        if name == "byte":  # an octet in ROS 2; rosbags packs it signed, so the two agree on 0-127
            return int(rng.integers(0, 128))
        info = np.iinfo(np.dtype(_NUMPY.get(name, name)))
        return int(rng.integers(max(info.min, -1000), min(info.max, 1000), endpoint=True))
    inner, count = spec
    n = count if kind == Nodetype.ARRAY else size
    if inner[0] == Nodetype.BASE and inner[1][0] not in ("string", "bool"):
        dtype = np.dtype(_NUMPY.get(inner[1][0], inner[1][0]))
        values = rng.standard_normal(n) if dtype.kind == "f" else rng.integers(0, 100, n)
        return values.astype(dtype)
    return [_value(inner, rng, size, Nodetype) for _ in range(n)]


_NUMPY = {"byte": "uint8", "char": "uint8"}


def declared(value, msgtype: str):
    """The same message as an instance of the cyclonedds declaration (nested types through their own)."""
    cls = wire_type(msgtype)
    return cls(**{name: _declared(getattr(value, name), node, cls.__annotations__[name])
                  for name, node in typestore().fielddefs[msgtype][1]})


def _declared(value, node, annotation):
    from rosbags.typesys.base import Nodetype

    kind, spec = node
    if kind == Nodetype.NAME:
        nested = annotation
        return nested(**{n: _declared(getattr(value, n), sub, nested.__annotations__[n])
                         for n, sub in typestore().fielddefs[spec][1]})
    if kind == Nodetype.BASE:
        return value
    inner = spec[0]
    if inner[0] == Nodetype.NAME:
        element = annotation.__metadata__[0].subtype if hasattr(annotation, "__metadata__") else None
        return [_declared(v, inner, element) for v in value]
    if isinstance(value, np.ndarray) and value.dtype == np.uint8:
        return value.tobytes()
    return [v.item() if hasattr(v, "item") else v for v in value]


@pytest.mark.parametrize("msgtype", MESSAGE_TYPES)
def test_each_declared_type_encodes_as_rosbags_does(msgtype):
    """cyclonedds' own encoding of the declared fields is rosbags' CDR, byte for byte: the type a ROS 2 peer sees
    and the bytes seqvpr sends agree."""
    from cyclonedds.idl import IdlStruct

    value = sample(msgtype, np.random.default_rng(len(msgtype)))
    expected = encode(value, msgtype)
    assert IdlStruct.serialize(declared(value, msgtype)) == expected
    assert outgoing(msgtype, value).serialize() == expected
    back = wire_type(msgtype).deserialize(expected)
    assert encode(back.message, msgtype) == expected and back.data == expected


@settings(max_examples=25, deadline=None)
@given(st.sampled_from([IMAGE, COMPRESSED, STATUS, NAVSATFIX]), st.integers(0, 2**32 - 1), st.integers(0, 40))
def test_random_messages_encode_as_rosbags_does(msgtype, seed, size):
    from cyclonedds.idl import IdlStruct

    value = sample(msgtype, np.random.default_rng(seed), size)
    assert IdlStruct.serialize(declared(value, msgtype)) == encode(value, msgtype)


def test_names_on_dds_are_ros2s():
    assert dds_typename(POSE) == "geometry_msgs::msg::dds_::PoseWithCovarianceStamped_"
    assert dds_topic("/seqvpr/pose") == "rt/seqvpr/pose"
    assert wire_type(EMPTY).__idl_typename__ == "std_msgs::msg::dds_::Empty_"
    assert {ODOMETRY, NAVSATFIX, IMAGE, COMPRESSED} <= set(MESSAGE_TYPES)


@pytest.mark.slow
def test_the_bytes_on_the_wire_are_rosbags_cdr(dds):
    """A message sent over DDS (loopback) arrives as the bytes rosbags writes for it (the transport pads to 4)."""
    from seqvpr.ros2.dds import EVERY_SAMPLE, Bus, wait_for_match

    value = sample(IMAGE, np.random.default_rng(5), size=999)
    collector = Recorder("/camera/image_raw", IMAGE)
    try:
        writer = Bus().writer("/camera/image_raw", IMAGE, EVERY_SAMPLE)
        assert wait_for_match(writer, 10)
        writer.write(outgoing(IMAGE, value))
        got = collector.wait_for(1, 10)
    finally:
        collector.close()
    expected = encode(value, IMAGE)
    data = got[0].data
    assert data[: len(expected)] == expected and not any(data[len(expected):]) and len(data) - len(expected) < 4
    assert decode(data, IMAGE).encoding == value.encoding
    assert np.array_equal(got[0].message.data, value.data)


def test_received_images_are_not_copied_into_python_lists():
    """A frame's pixels come back as a NumPy array over the bytes (what keeps a 1 MB frame's decode cheap)."""
    pixels = np.random.default_rng(0).integers(0, 255, 640 * 480 * 3, dtype=np.uint8)
    value = sample(IMAGE, np.random.default_rng(1))
    value.data = pixels
    back = wire_type(IMAGE).deserialize(encode(value, IMAGE))
    assert isinstance(back.message.data, np.ndarray) and np.array_equal(back.message.data, pixels)


def test_bytes_that_are_not_the_type_are_a_received_error_not_an_exception():
    """cyclonedds checks CDR against the type on both ends, so a peer cannot send such bytes; should any arrive,
    the reader thread gets a Received naming them (the node counts it as a malformed frame), never an exception."""
    got = wire_type(IMAGE).deserialize(b"\0\1\0\0\7\7\7")
    assert got.message is None and got.data == b"\0\1\0\0\7\7\7"
    assert "7 bytes that are not a sensor_msgs/msg/Image" in got.error
