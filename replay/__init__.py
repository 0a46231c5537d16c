"""streamdet.replay: a drive played at sensor rates through the runtime, every detection scored when it is emitted.

torch-free (numpy, onnxruntime through streamdet.runtime_ort). One concept per module:

- ``source``: the player's input, a `Drive` of timed LiDAR sweeps and camera image sets (``nuscenes_source``
  builds one from a nuScenes-format dataset; another source, e.g. a ROS 2 bag, plugs in the same way);
- ``schedule``: when each slice / image set is released (last point scanned; capture time);
- ``clock``: the wall clock, a deterministic fake clock for tests, drive time at a time scale;
- ``modes``: streaming (two lanes), full-sweep, sequential (one queue);
- ``player``: plays a drive through a mode from its own thread and records every release (``record``);
- ``truth`` / ``latency_eval``: ground truth at any time and nuScenes mAP at emission time vs scan time;
- ``run``: a whole replay (scenes x modes through a real export); ``report`` / ``plot`` / ``cli``: the table, JSON,
  timeline picture and ``streamdet-replay``; ``cost``: the player's own CPU with a no-op detector.

docs/replay.md describes the whole; README "Streaming in real time" has the figures.
"""
