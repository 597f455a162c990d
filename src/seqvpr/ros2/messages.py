"""The ROS 2 messages seqvpr sends and reads over DDS, defined once: from the ``rosbags`` type store (ROS 2 Humble's
message definitions), so the wire format is the one ``rosbags`` reads and writes in bags and cannot drift.

Each message type becomes a cyclonedds type (``wire_type``) named as ROS 2 names it on DDS
(``sensor_msgs::msg::dds_::Image_``), declared field by field from the same definitions, so a ROS 2 participant
sees the type it knows. Its samples are encoded and decoded by ``rosbags``' CDR codec: a received sample is a
``Received`` (the ``rosbags`` message and the bytes that came), a sent one is an ``outgoing`` sample (bytes from a
``rosbags`` message, or a bag's own bytes as they are). ``tests/ros2/test_messages.py`` holds the declared types'
own serialisation against ``rosbags``' bytes for every type here.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field
from typing import Any

#: every ROS 2 message type seqvpr's node and player use, by ROS 2 name
IMAGE, COMPRESSED = "sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage"
NAVSATFIX, ODOMETRY = "sensor_msgs/msg/NavSatFix", "nav_msgs/msg/Odometry"
POSE, STATUS, EMPTY = "geometry_msgs/msg/PoseWithCovarianceStamped", "diagnostic_msgs/msg/DiagnosticArray", \
    "std_msgs/msg/Empty"
PATH = "nav_msgs/msg/Path"
MESSAGE_TYPES = (IMAGE, COMPRESSED, NAVSATFIX, ODOMETRY, POSE, STATUS, EMPTY, PATH)


@functools.cache
def typestore():
    """The ``rosbags`` type store of ROS 2 Humble: the source of truth for every message's fields."""
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS2_HUMBLE)


def message(msgtype: str, **fields: Any):
    """A ``rosbags`` message of ``msgtype`` (every field given, as ``rosbags`` takes them)."""
    return typestore().types[msgtype](**fields)


def encode(value: Any, msgtype: str) -> bytes:
    """The CDR bytes (little-endian, with the 4-byte encapsulation header) of a ``rosbags`` message."""
    return bytes(typestore().serialize_cdr(value, msgtype))


def decode(data: bytes, msgtype: str):
    """The ``rosbags`` message of CDR bytes (a uint8 sequence comes back as a NumPy array over the bytes)."""
    return typestore().deserialize_cdr(data, msgtype)


def dds_typename(msgtype: str) -> str:
    """The type's name on DDS, as ROS 2 writes it: ``pkg/msg/Name`` -> ``pkg::msg::dds_::Name_``."""
    package, kind, name = msgtype.split("/")
    return f"{package}::{kind}::dds_::{name}_"


def dds_topic(topic: str) -> str:
    """A ROS 2 topic's name on DDS: ``/seqvpr/pose`` -> ``rt/seqvpr/pose``."""
    return "rt/" + topic.lstrip("/")


@dataclass
class Received:
    """A sample as it came: the ``rosbags`` message (None where the bytes do not decode as its type: ``error``
    says why) and its bytes (``sample_info`` is set by cyclonedds)."""

    message: Any
    data: bytes
    error: str = ""
    sample_info: Any = field(default=None, repr=False)


@functools.cache
def wire_type(msgtype: str) -> type:
    """The cyclonedds type of ``msgtype``: its fields declared from the type store (nested types the same way), its
    samples through ``rosbags``' codec. ``deserialize`` gives a ``Received``; ``outgoing`` makes the samples a
    writer sends. (cyclonedds' own encoding of the declared fields stays reachable as ``IdlStruct.serialize``: the
    test that holds it equal to ``rosbags``' bytes.)"""
    declared = _declaration(msgtype)

    def deserialize(cls, data: bytes, has_header: bool = True, use_version_2: bool | None = None) -> Received:
        raw = bytes(data)
        try:
            return Received(decode(raw, msgtype), raw)
        except Exception as error:  # a peer's malformed bytes: reported by whoever reads them, never a dead reader
            return Received(None, raw, f"{len(raw)} bytes that are not a {msgtype} ({type(error).__name__})")

    def serialize(self, buffer=None, endianness=None, use_version_2=None) -> bytes:
        return self._seqvpr_bytes

    declared.deserialize, declared.serialize = classmethod(deserialize), serialize
    return declared


def outgoing(msgtype: str, value: Any = None, *, data: bytes | None = None):
    """A sample of ``wire_type(msgtype)`` to write: a ``rosbags`` message encoded, or ``data``, CDR bytes as they
    are (a bag's own message)."""
    cls = wire_type(msgtype)
    sample = object.__new__(cls)
    sample._seqvpr_bytes = data if data is not None else encode(value, msgtype)
    return sample


#: ROS 2 primitive types as cyclonedds declares them (``byte`` and ``char`` are octets in ROS 2)
_BASE = ("bool", "byte", "char", "int8", "uint8", "int16", "uint16", "int32", "uint32", "int64", "uint64", "float32",
         "float64")


def _field_type(node: tuple) -> Any:
    """A type-store field node (BASE, NAME, ARRAY or SEQUENCE) as a cyclonedds annotation."""
    import cyclonedds.idl.types as t
    from rosbags.typesys.base import Nodetype

    kind, spec = node
    if kind == Nodetype.BASE:
        name, bound = spec
        if name == "string":
            return t.bounded_str[bound] if bound else str
        if name not in _BASE:
            raise TypeError(f"ROS 2 type {name!r} has no DDS declaration here")
        return bool if name == "bool" else getattr(t, {"byte": "uint8", "char": "uint8"}.get(name, name))
    if kind == Nodetype.NAME:
        return _nested_type(spec)
    inner, size = spec
    if kind == Nodetype.ARRAY:
        return t.array[_field_type(inner), size]
    return t.sequence[_field_type(inner), size] if size else t.sequence[_field_type(inner)]


def _declaration(msgtype: str) -> type:
    """A new cyclonedds struct of ``msgtype``'s fields, named as ROS 2 names it on DDS."""
    from cyclonedds.idl import make_idl_struct

    fields = {name: _field_type(node) for name, node in typestore().fielddefs[msgtype][1]}
    return make_idl_struct(msgtype.rsplit("/", 1)[1], dds_typename(msgtype), fields)


#: a message type inside another, declared with cyclonedds' own codec (it is never sent alone)
_nested_type = functools.cache(_declaration)
