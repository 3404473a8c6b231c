"""ROS 2 message types for the arm drivers: definitions, names and CDR, from ``rosbags``.

A ROS 2 type such as ``sensor_msgs/msg/JointState`` travels over DDS as the type
``sensor_msgs::msg::dds_::JointState_``, in XCDR1 little-endian (``00 01 00 00`` encapsulation header), on the topic
``rt/<ros topic without its leading slash>``; since Jazzy each endpoint also carries the type's RIHS01 hash in its
USER_DATA (``typehash=RIHS01_<sha256>;``). ``rosbags`` holds the ROS 2 Jazzy message definitions (plus
``interbotix_xs_msgs/msg/JointGroupCommand``, registered here from the Interbotix repository's .msg text), computes
the hashes and serializes; ``idl_type`` builds the matching ``cyclonedds`` IDL struct from the same definition, which
cyclonedds needs to create a topic (its type name and XTypes type information), while the bytes on the wire are
rosbags' own.

rosbags serializes and deserializes a JointState as fast as a hand-written ``struct`` / numpy reader of the same
layout, so rosbags does all of it (docs/howto/real-robots.md has the comparison with cyclonedds' own serializer).
"""

from __future__ import annotations

import functools
from typing import Any

from uniros_async.errors import CodecError, ConfigError

__all__ = [
    "ENCAPSULATION_CDR_LE",
    "INTERBOTIX_JOINT_GROUP_COMMAND",
    "dds_topic_name",
    "dds_type_name",
    "deserialize",
    "idl_type",
    "ros_type_name",
    "serialize",
    "type_hash",
    "typestore",
]

ENCAPSULATION_CDR_LE = b"\x00\x01\x00\x00"

INTERBOTIX_JOINT_GROUP_COMMAND = """\
# Command the joints in the specified joint group. Note that the commands are processed differently based on the group's operating mode.
# For example, if a group's operating mode is set to 'position', the commands are interpreted as positions in radians

string name            # Name of joint group
float32[] cmd          # List of joint commands; order is dictated by the index of each joint name for the given group in the 'groups' section of a 'motor_config' yaml file
"""  # noqa: E501
"""``interbotix_xs_msgs/msg/JointGroupCommand`` as the ROS 2 xs_sdk defines it: the text of
``interbotix_ros_xseries/interbotix_xs_msgs/msg/JointGroupCommand.msg`` in github.com/Interbotix/interbotix_ros_core,
branch ``jazzy`` (commit bf127b474e0554b93ef18b51becba38da9cbc255; identical on ``humble``). Its package is not on
PyPI, so it is registered with rosbags from this text."""


@functools.cache
def typestore() -> Any:
    """The rosbags type store: ROS 2 Jazzy's messages plus the Interbotix JointGroupCommand."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.ROS2_JAZZY)
    store.register(get_types_from_msg(INTERBOTIX_JOINT_GROUP_COMMAND, "interbotix_xs_msgs/msg/JointGroupCommand"))
    return store


def ros_type_name(name: str) -> str:
    """``sensor_msgs/JointState`` or ``sensor_msgs/msg/JointState`` -> ``sensor_msgs/msg/JointState``.

    Raises:
        ConfigError: not a ``pkg/[msg/]Name`` type name.
    """
    parts = name.strip("/").split("/")
    if len(parts) == 2:
        parts.insert(1, "msg")
    if len(parts) != 3 or not all(parts) or parts[1] != "msg":
        raise ConfigError(f"expected a ROS 2 message type like sensor_msgs/msg/JointState, got {name!r}")
    return "/".join(parts)


def dds_type_name(ros_type: str) -> str:
    """``sensor_msgs/msg/JointState`` -> ``sensor_msgs::msg::dds_::JointState_`` (the rmw's DDS type name)."""
    pkg, sub, name = ros_type_name(ros_type).split("/")
    return f"{pkg}::{sub}::dds_::{name}_"


def ros_type_from_dds(dds_type: str) -> str:
    """``sensor_msgs::msg::dds_::JointState_`` -> ``sensor_msgs/msg/JointState``; other names come back as given."""
    parts = dds_type.split("::")
    if len(parts) == 4 and parts[2] == "dds_" and parts[3].endswith("_"):
        return f"{parts[0]}/{parts[1]}/{parts[3][:-1]}"
    return dds_type


def dds_topic_name(topic: str) -> str:
    """An absolute ROS 2 topic ``/rx200/joint_states`` -> its DDS topic ``rt/rx200/joint_states``.

    Raises:
        ConfigError: not an absolute topic name.
    """
    if not topic.startswith("/") or len(topic) < 2 or topic.endswith("/") or "//" in topic:
        raise ConfigError(f"expected an absolute ROS 2 topic name like /rx200/joint_states, got {topic!r}")
    return "rt" + topic


@functools.cache
def type_hash(ros_type: str) -> str:
    """The type's RIHS01 hash (``RIHS01_<hex>``), as Jazzy's rmw put it in an endpoint's USER_DATA.

    Raises:
        ConfigError: a type the store does not know.
    """
    return str(typestore().hash_rihs01(_known(ros_type)))


def _known(ros_type: str) -> str:
    name = ros_type_name(ros_type)
    if name not in typestore().types:
        raise ConfigError(f"unknown ROS 2 message type {name!r} (rosbags' Jazzy store has no such message)")
    return name


def message_class(ros_type: str) -> Any:
    """The rosbags class of ``ros_type`` (a dataclass; arrays of numbers are numpy arrays)."""
    return typestore().types[_known(ros_type)]


@functools.cache
def _codec(ros_type: str) -> tuple[Any, Any, Any, Any, Any]:
    """rosbags' generated functions of ``ros_type``: (size, serialize LE, deserialize LE, deserialize BE, class)."""
    msgdef = typestore().get_msgdef(_known(ros_type))
    return (
        msgdef.getsize_cdr,
        msgdef.serialize_cdr_le,
        msgdef.deserialize_cdr_le,
        msgdef.deserialize_cdr_be,
        msgdef.cls,
    )


def serialize(msg: Any, ros_type: str) -> bytes:
    """``msg`` (a rosbags message) -> CDR bytes with the encapsulation header, as a DDS writer sends them."""
    size, ser, _, _, _ = _codec(ros_type)
    store = typestore()
    out = bytearray(4 + size(0, msg, store))
    out[1] = 1  # CDR_LE
    ser(memoryview(out)[4:], 0, msg, store)
    return bytes(out)


def deserialize(data: bytes | memoryview, ros_type: str) -> Any:
    """CDR bytes (with the encapsulation header) -> a rosbags message.

    Raises:
        CodecError: the bytes do not hold a ``ros_type`` (names the type).
    """
    if len(data) < 4 or data[0] != 0 or data[1] > 1:
        raise CodecError(f"{ros_type}: {bytes(data[:4])!r} is not a plain CDR encapsulation header")
    _, _, de_le, de_be, cls = _codec(ros_type)
    try:
        # rosbags' deserialize_cdr also refuses trailing bytes; an rmw may send a few (its size estimate), as
        # rclpy's serialize_message does, so the reader stops at the message's end instead
        return (de_le if data[1] else de_be)(memoryview(data)[4:], 0, cls, typestore())[0]
    except Exception as exc:  # struct.error, IndexError, ValueError, UnicodeDecodeError on bad input
        raise CodecError(f"{ros_type}: {len(data)} bytes are not a valid CDR message: {exc}") from exc


# ----------------------------------------------------------------------------------------- cyclonedds IDL types


_IDL_BASE = {
    "bool": "bool",
    "byte": "byte",
    "char": "uint8",
    "int8": "int8",
    "uint8": "uint8",
    "int16": "int16",
    "uint16": "uint16",
    "int32": "int32",
    "uint32": "uint32",
    "int64": "int64",
    "uint64": "uint64",
    "float32": "float32",
    "float64": "float64",
}


@functools.cache
def idl_type(ros_type: str) -> Any:
    """A cyclonedds IDL struct of ``ros_type``, named as the rmw names it (``pkg::msg::dds_::Name_``), built from
    rosbags' definition; cyclonedds makes the topic and its type information from it."""
    from cyclonedds.idl import make_idl_struct, types
    from rosbags.interfaces import Nodetype

    store = typestore()
    name = _known(ros_type)
    msgdef = store.get_msgdef(name)
    t: Any = types  # its generic aliases (sequence[T], array[T, n]) are not typed as generics

    def field_type(desc: Any) -> Any:
        kind, arg = desc
        if kind == Nodetype.BASE:
            base, bound = arg
            if base == "string":
                return t.bounded_str[bound] if bound else str
            if base == "bool":
                return bool
            return getattr(t, _IDL_BASE[base])
        if kind == Nodetype.NAME:
            return idl_type(arg)
        if kind == Nodetype.ARRAY:
            sub, n = arg
            return t.array[field_type(sub), n]
        if kind == Nodetype.SEQUENCE:
            sub, bound = arg
            return t.sequence[field_type(sub), bound] if bound else t.sequence[field_type(sub)]
        raise ConfigError(f"{name}: field kind {kind} has no IDL mapping")

    fields = {fname: field_type(desc) for fname, desc in msgdef.fields}
    if not fields:  # an empty ROS message is a struct with one uint8 (as rosidl generates it)
        fields = {"structure_needs_at_least_one_member": t.uint8}
    return make_idl_struct(name.replace("/", "__"), dds_type_name(name), fields)
