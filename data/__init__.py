"""streamdet.data: samples, streaming slices, the nuScenes reader and the synthetic world (numpy + OpenCV only).

- ``sample``: ``Sample`` / ``Sweep``, ``load_image``, ``load_points``, ``load_bundled_sample`` (the shipped real sample)
- ``slicing``: ``split_sweep``, ``boxes_in_sector``, ``slice_sample`` -> ``Slice``
- ``nuscenes``: ``NuScenesReader`` (official JSON tables, no devkit needed)
- ``synth_world`` / ``synth_lidar`` / ``synth_render`` / ``synth_materials`` / ``synth_raycast`` / ``synth_writer``:
  the synthetic street, its rolling 32-beam LiDAR, its cameras and the nuScenes-format writer (``streamdet-synth``)
- ``preview``: ``draw_bev``, ``draw_camera_boxes``, ``write_previews``
"""

from streamdet.core.slicing import boxes_in_sector, split_sweep
from streamdet.data.nuscenes import NuScenesReader
from streamdet.data.sample import Sample, Sweep, load_bundled_sample, load_image, load_points
from streamdet.data.slicing import Slice, slice_sample

__all__ = [
    "NuScenesReader",
    "Sample",
    "Slice",
    "Sweep",
    "boxes_in_sector",
    "load_bundled_sample",
    "load_image",
    "load_points",
    "slice_sample",
    "split_sweep",
]
