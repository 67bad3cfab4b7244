"""The ROS 2 `.msg` definitions of the messages a recording carries, and the schema text an MCAP
ros2msg channel needs (`schema_text`).

A ROS 2 MCAP channel (message encoding `cdr`, schema encoding `ros2msg`) carries the type's `.msg`
text followed by every type it uses, each after a two-line delimiter (80 `=`, then `MSG: pkg/Type`):
what Foxglove, mcap_ros2 and `ros2 bag` decode the bytes with. `schema_text` builds it the way
rosbag2 does (its LocalMessageDefinitionSource): a definition's dependencies are the non-primitive
field types named at the start of its lines (an unqualified name is in the definition's own
package), visited in sorted order, depth first, each written once, with a newline before each
delimiter.

The texts are ROS 2 Jazzy's `share/<pkg>/msg/<Type>.msg` files, copied verbatim (a trailing
space is written as the escape `\\x20`); tf2_msgs is not installed here, so its one-line
TFMessage.msg is written out. The sensor messages' texts are in msg_definitions_sensors.py. To record another type, add its text and those of the types it uses
(tests compare them with the installed files).
"""
from __future__ import annotations

import re

from runtime.io.ros.msg_definitions_sensors import SENSOR_DEFINITIONS

SEPARATOR = "=" * 80

#: `pkg/Type` -> the .msg text.
DEFINITIONS: dict[str, str] = {
    "builtin_interfaces/Time": """\
# This message communicates ROS Time defined here:
# https://design.ros2.org/articles/clock_and_time.html

# The seconds component, valid over all int32 values.
int32 sec

# The nanoseconds component, valid in the range [0, 1e9), to be added to the seconds component.\x20
# e.g.
# The time -1.7 seconds is represented as {sec: -2, nanosec: 3e8}
# The time 1.7 seconds is represented as {sec: 1, nanosec: 7e8}
uint32 nanosec
""",
    "std_msgs/Header": """\
# Standard metadata for higher-level stamped data types.
# This is generally used to communicate timestamped data
# in a particular coordinate frame.

# Two-integer timestamp that is expressed as seconds and nanoseconds.
builtin_interfaces/Time stamp

# Transform frame with which this data is associated.
string frame_id
""",
    "geometry_msgs/Vector3": """\
# This represents a vector in free space.

# This is semantically different than a point.
# A vector is always anchored at the origin.
# When a transform is applied to a vector, only the rotational component is applied.

float64 x
float64 y
float64 z
""",
    "geometry_msgs/Quaternion": """\
# This represents an orientation in free space in quaternion form.

float64 x 0
float64 y 0
float64 z 0
float64 w 1
""",
    "geometry_msgs/Transform": """\
# This represents the transform between two coordinate frames in free space.

Vector3 translation
Quaternion rotation
""",
    "geometry_msgs/TransformStamped": """\
# This expresses a transform from coordinate frame header.frame_id
# to the coordinate frame child_frame_id at the time of header.stamp
#
# This message is mostly used by the
# <a href="https://docs.ros.org/en/rolling/p/tf2/">tf2</a> package.
# See its documentation for more information.
#
# The child_frame_id is necessary in addition to the frame_id
# in the Header to communicate the full reference for the transform
# in a self contained message.

# The frame id in the header is used as the reference frame of this transform.
std_msgs/Header header

# The frame id of the child frame to which this transform points.
string child_frame_id

# Translation and rotation in 3-dimensions of child_frame_id from header.frame_id.
Transform transform
""",
    "tf2_msgs/TFMessage": """\
geometry_msgs/TransformStamped[] transforms
""",
    **SENSOR_DEFINITIONS,  # the sensor messages recorded as received (msg_definitions_sensors.py)
}

_PRIMITIVES = frozenset({"bool", "byte", "char", "float32", "float64", "int8", "uint8", "int16", "uint16", "int32",
                         "uint32", "int64", "uint64", "string", "wstring"})
# A field's type at the start of a line ("geometry_msgs/TransformStamped" in "...TransformStamped[] transforms").
_FIELD_TYPE = re.compile(r"(?:^|\n)\s*([a-zA-Z0-9_/]+)(?:\[[^\]]*\])?\s+")


def short_name(type_name: str) -> str:
    """`pkg/msg/Type` or `pkg/Type` -> `pkg/Type`."""
    parts = type_name.split("/")
    if len(parts) == 3 and parts[1] == "msg" and all(parts):
        return f"{parts[0]}/{parts[2]}"
    if len(parts) == 2 and all(parts):
        return type_name
    raise ValueError(f"{type_name!r} is not a ROS 2 message type name (pkg/msg/Type)")


def _definition(name: str) -> str:
    try:
        return DEFINITIONS[name]
    except KeyError:
        raise KeyError(f"no .msg definition for {name} (runtime.io.ros.msg_definitions.DEFINITIONS)") from None


def dependencies(type_name: str) -> list[str]:
    """The message types a definition's fields name (`pkg/Type`), sorted."""
    name = short_name(type_name)
    package = name.split("/")[0]
    found = set()
    for m in _FIELD_TYPE.finditer(_definition(name)):
        t = m.group(1)
        if t not in _PRIMITIVES:
            found.add(t if "/" in t else f"{package}/{t}")
    return sorted(found)


def schema_text(type_name: str) -> str:
    """The ros2msg schema of `type_name` (`pkg/msg/Type`): its definition, then each type it uses."""
    seen: set[str] = set()

    def append(name: str, depth: int) -> str:
        if depth <= 0:
            raise ValueError(f"{type_name}: message definitions nest too deep (a cycle?)")
        out = _definition(name)
        for dep in dependencies(name):
            if dep not in seen:
                seen.add(dep)
                out += f"\n{SEPARATOR}\nMSG: {dep}\n" + append(dep, depth - 1)
        return out

    return append(short_name(type_name), 50)
