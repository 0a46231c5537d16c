"""ROS 2 message adapters: a driver's messages in, numpy out, and detections back out as messages.

Torch-free and free of any ROS or MCAP library. Incoming messages are read through their ROS field attributes
(``msg.header.stamp.sec``, ``msg.fields[i].datatype``, ...), which is what rclpy, mcap-ros2-support and rosbags all
decode to; ``uint8[]`` payloads may be ``bytes``, ``array.array`` or numpy arrays. Outgoing messages are nested
dicts keyed by the ROS field names: mcap-ros2-support encodes them as they are, and an rclpy node fills a message
class from one with ``rosidl_runtime_py.set_message_fields(Detection3DArray(), d)``.

- ``pointcloud2``: ``sensor_msgs/PointCloud2`` -> ``Cloud`` (the runtime's (N, 5) sweep plus per-point time), its
  slices (``split_cloud``, or ``slice_from_message`` when the driver already publishes slices), and back;
- ``images``: ``sensor_msgs/Image`` (rgb8, bgr8, rgba8, bgra8) and ``sensor_msgs/CompressedImage`` (jpeg, png) -> RGB;
- ``tf``: a numpy TF buffer over ``tf2_msgs/TFMessage`` (``/tf`` and ``/tf_static``);
- ``camera_info``: ``sensor_msgs/CameraInfo`` + TF -> the ``Rig`` the projection LUT is built from;
- ``detections``: ``Detections`` -> ``vision_msgs/Detection3DArray`` and ``visualization_msgs/MarkerArray``.

Every refusal of a message is a ``RosMessageError`` (a ValueError, exported by ``streamdet.runtime_ort``) naming the
message, the field and the value, so a node catches it per message and goes on; ``CloudClockError`` (a cloud's
per-point clock or unit is not its header's) and ``TfLookupError`` (no TF path, or a stamp outside the kept ones)
are subclasses. Wrong arguments (a ``CloudFields`` or ``TfBuffer`` setting) stay plain ValueErrors.

docs/ros2.md shows how a ROS 2 node and ``streamdet-bag`` use them.
"""
