"""The ROS 2 message definitions (Humble) of the topics ``streamdet-bag`` writes, as text.

An MCAP ``ros2msg`` schema is the top-level definition followed by every definition it uses, each after a
``====`` line and a ``MSG: pkg/Type`` line: what ``ros2 bag record`` writes and what Foxglove, rosbags and
mcap-ros2-support read. ``schema_text`` assembles that from the definitions below (comments dropped, constants,
defaults and field order as in the packages' .msg files).
"""

from __future__ import annotations

import re

SEPARATOR = "=" * 80

MSGDEFS: dict[str, str] = {
    "builtin_interfaces/Time": """
int32 sec
uint32 nanosec
""",
    "builtin_interfaces/Duration": """
int32 sec
uint32 nanosec
""",
    "std_msgs/Header": """
builtin_interfaces/Time stamp
string frame_id
""",
    "std_msgs/ColorRGBA": """
float32 r
float32 g
float32 b
float32 a
""",
    "geometry_msgs/Point": """
float64 x
float64 y
float64 z
""",
    "geometry_msgs/Vector3": """
float64 x
float64 y
float64 z
""",
    "geometry_msgs/Quaternion": """
float64 x 0
float64 y 0
float64 z 0
float64 w 1
""",
    "geometry_msgs/Pose": """
Point position
Quaternion orientation
""",
    "geometry_msgs/PoseWithCovariance": """
Pose pose
float64[36] covariance
""",
    "geometry_msgs/Transform": """
Vector3 translation
Quaternion rotation
""",
    "geometry_msgs/TransformStamped": """
std_msgs/Header header
string child_frame_id
Transform transform
""",
    "tf2_msgs/TFMessage": """
geometry_msgs/TransformStamped[] transforms
""",
    "sensor_msgs/PointField": """
uint8 INT8    = 1
uint8 UINT8   = 2
uint8 INT16   = 3
uint8 UINT16  = 4
uint8 INT32   = 5
uint8 UINT32  = 6
uint8 FLOAT32 = 7
uint8 FLOAT64 = 8
string name
uint32 offset
uint8  datatype
uint32 count
""",
    "sensor_msgs/PointCloud2": """
std_msgs/Header header
uint32 height
uint32 width
PointField[] fields
bool    is_bigendian
uint32  point_step
uint32  row_step
uint8[] data
bool is_dense
""",
    "sensor_msgs/CompressedImage": """
std_msgs/Header header
string format
uint8[] data
""",
    "sensor_msgs/Image": """
std_msgs/Header header
uint32 height
uint32 width
string encoding
uint8 is_bigendian
uint32 step
uint8[] data
""",
    "sensor_msgs/RegionOfInterest": """
uint32 x_offset
uint32 y_offset
uint32 height
uint32 width
bool do_rectify
""",
    "sensor_msgs/CameraInfo": """
std_msgs/Header header
uint32 height
uint32 width
string distortion_model
float64[] d
float64[9]  k
float64[9]  r
float64[12] p
uint32 binning_x
uint32 binning_y
RegionOfInterest roi
""",
    "visualization_msgs/UVCoordinate": """
float32 u
float32 v
""",
    "visualization_msgs/MeshFile": """
string filename
uint8[] data
""",
    "visualization_msgs/Marker": """
int32 ARROW=0
int32 CUBE=1
int32 SPHERE=2
int32 CYLINDER=3
int32 LINE_STRIP=4
int32 LINE_LIST=5
int32 CUBE_LIST=6
int32 SPHERE_LIST=7
int32 POINTS=8
int32 TEXT_VIEW_FACING=9
int32 MESH_RESOURCE=10
int32 TRIANGLE_LIST=11
int32 ADD=0
int32 MODIFY=0
int32 DELETE=2
int32 DELETEALL=3
std_msgs/Header header
string ns
int32 id
int32 type
int32 action
geometry_msgs/Pose pose
geometry_msgs/Vector3 scale
std_msgs/ColorRGBA color
builtin_interfaces/Duration lifetime
bool frame_locked
geometry_msgs/Point[] points
std_msgs/ColorRGBA[] colors
string texture_resource
sensor_msgs/CompressedImage texture
UVCoordinate[] uv_coordinates
string text
string mesh_resource
MeshFile mesh_file
bool mesh_use_embedded_materials
""",
    "visualization_msgs/MarkerArray": """
Marker[] markers
""",
    "vision_msgs/ObjectHypothesis": """
string class_id
float64 score
""",
    "vision_msgs/ObjectHypothesisWithPose": """
ObjectHypothesis hypothesis
geometry_msgs/PoseWithCovariance pose
""",
    "vision_msgs/BoundingBox3D": """
geometry_msgs/Pose center
geometry_msgs/Vector3 size
""",
    "vision_msgs/Detection3D": """
std_msgs/Header header
ObjectHypothesisWithPose[] results
BoundingBox3D bbox
string id
""",
    "vision_msgs/Detection3DArray": """
std_msgs/Header header
Detection3D[] detections
""",
}

PRIMITIVES = frozenset(
    "bool byte char float32 float64 int8 uint8 int16 uint16 int32 uint32 int64 uint64 string wstring".split()
)


def short_name(datatype: str) -> str:
    """``pkg/Type`` of ``pkg/msg/Type`` or ``pkg/Type``."""
    parts = datatype.split("/")
    if len(parts) == 3 and parts[1] == "msg":
        return f"{parts[0]}/{parts[2]}"
    if len(parts) != 2:
        raise ValueError(f"not a ROS 2 message type name: {datatype!r}")
    return datatype


def full_name(datatype: str) -> str:
    """``pkg/msg/Type``, the schema name rosbag2 writes."""
    pkg, name = short_name(datatype).split("/")
    return f"{pkg}/msg/{name}"


def definition(datatype: str) -> str:
    """The bare definition text of one type."""
    name = short_name(datatype)
    if name not in MSGDEFS:
        raise KeyError(f"no message definition for {datatype!r}; streamdet.bag knows {sorted(MSGDEFS)}")
    return MSGDEFS[name].strip()


def dependencies(datatype: str) -> list[str]:
    """The types one definition's fields name, as ``pkg/Type``, in field order."""
    pkg = short_name(datatype).split("/")[0]
    out = []
    for line in definition(datatype).splitlines():
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        type_token, rest = line.split(None, 1)
        if "=" in rest:  # a constant
            continue
        base = re.sub(r"\[.*\]$", "", type_token)
        base = re.sub(r"<=\d+$", "", base)
        if base in PRIMITIVES:
            continue
        out.append(base if "/" in base else f"{pkg}/{base}")
    return out


def schema_text(datatype: str) -> str:
    """The full ``ros2msg`` schema of a type: its definition, then each dependency once, depth first."""
    order: list[str] = []

    def visit(name: str) -> None:
        for dep in dependencies(name):
            if dep not in order:
                order.append(dep)
                visit(dep)

    visit(short_name(datatype))
    parts = [definition(datatype)]
    parts += [f"{SEPARATOR}\nMSG: {dep}\n{definition(dep)}" for dep in order]
    return "\n".join(parts) + "\n"
