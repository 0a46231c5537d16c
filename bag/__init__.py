"""streamdet.bag: ROS 2 MCAP bags in and out (``streamdet-bag``), without a ROS installation.

``export`` writes a nuScenes-format scene as the bag a car records (``/LIDAR_TOP``, ``/CAM_*/image_rect_compressed``,
``/CAM_*/camera_info``, ``/tf``, ``/tf_static``, ground truth as a MarkerArray); ``source`` reads a bag back as timed
slices and image sets; ``run`` feeds them through the torch-free detector and writes the detections as ROS 2
topics. The message adapters live in ``streamdet.runtime_ort.ros``; this package adds the MCAP files, through the
optional extra ``pip install '.[ros]'`` (from the repository root) (mcap, mcap-ros2-support).
"""
