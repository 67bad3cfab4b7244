"""tf2_msgs and visualization_msgs (ROS 2 Jazzy) as cyclonedds IDL structs: what RViz and Foxglove
draw the robot's frames and shapes from.

Same conventions as runtime.io.ros.messages_common (DDS name `pkg::msg::dds_::Name_`, the field
order and types of the Jazzy `.msg`, `uint8[]` as `bytes`); re-exported by
runtime.io.ros.messages, whose `ROS_TYPES` lists them. Jazzy's Marker carries texture and mesh
fields (texture_resource, texture, uv_coordinates, mesh_file, mesh_use_embedded_materials) that
Humble's does not: these are Jazzy's, and a Humble subscriber would not match the type.
"""

from dataclasses import dataclass, field

from cyclonedds.idl import IdlStruct
from cyclonedds.idl.types import float32, int32, sequence

from runtime.io.ros.messages_common import (
    ColorRGBA, CompressedImage, Duration, Header, Point, Pose, TransformStamped, Vector3,
)

# ----------------------------------------------------------------------------- tf2_msgs


@dataclass
class TFMessage(IdlStruct, typename="tf2_msgs::msg::dds_::TFMessage_"):
    """What /tf and /tf_static carry."""

    transforms: sequence[TransformStamped] = field(default_factory=list)


# ----------------------------------------------------------------------------- visualization_msgs


@dataclass
class UVCoordinate(IdlStruct, typename="visualization_msgs::msg::dds_::UVCoordinate_"):
    u: float32 = 0.0
    v: float32 = 0.0


@dataclass
class MeshFile(IdlStruct, typename="visualization_msgs::msg::dds_::MeshFile_"):
    filename: str = ""
    data: bytes = b""               # uint8[]


# Marker.type constants (visualization_msgs/msg/Marker.msg)
(ARROW, CUBE, SPHERE, CYLINDER, LINE_STRIP, LINE_LIST, CUBE_LIST, SPHERE_LIST, POINTS, TEXT_VIEW_FACING,
 MESH_RESOURCE, TRIANGLE_LIST, ARROW_STRIP) = range(13)
# Marker.action constants (MODIFY is ADD)
MARKER_ADD, MARKER_DELETE, MARKER_DELETEALL = 0, 2, 3


@dataclass
class Marker(IdlStruct, typename="visualization_msgs::msg::dds_::Marker_"):
    header: Header = field(default_factory=Header)
    ns: str = ""
    id: int32 = 0
    type: int32 = 0
    action: int32 = MARKER_ADD
    pose: Pose = field(default_factory=Pose)
    scale: Vector3 = field(default_factory=Vector3)
    color: ColorRGBA = field(default_factory=ColorRGBA)
    lifetime: Duration = field(default_factory=Duration)    # 0: forever
    frame_locked: bool = False
    points: sequence[Point] = field(default_factory=list)
    colors: sequence[ColorRGBA] = field(default_factory=list)
    texture_resource: str = ""
    texture: CompressedImage = field(default_factory=CompressedImage)
    uv_coordinates: sequence[UVCoordinate] = field(default_factory=list)
    text: str = ""
    mesh_resource: str = ""
    mesh_file: MeshFile = field(default_factory=MeshFile)
    mesh_use_embedded_materials: bool = False


@dataclass
class MarkerArray(IdlStruct, typename="visualization_msgs::msg::dds_::MarkerArray_"):
    markers: sequence[Marker] = field(default_factory=list)
