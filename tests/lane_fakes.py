"""Test helper (not a test module): a StreamingDetector stand-in for the lanes, with no graph behind it."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

CAMERAS = ("CAM_FRONT", "CAM_FRONT_RIGHT", "CAM_FRONT_LEFT", "CAM_BACK", "CAM_BACK_LEFT", "CAM_BACK_RIGHT")


class StandInDetector:
    """What StreamingRunner and both image schedules read of a StreamingDetector: every camera sees every quadrant,
    updates and slices return at once (subclasses gate or time them)."""

    uses_images = True
    num_slices = 8
    camera_names = CAMERAS
    config = SimpleNamespace(start_deg=0.0, clockwise=False)

    def quadrant_cameras(self, quadrants):
        return self.camera_names

    def check_images(self, images) -> None:
        pass

    def encode_images(self, images):
        return {n: np.zeros((1, 1, 1), np.float32) for n in images}

    def update_images(self, images, timestamp=None, quadrants=None, encoded=None, camera_timestamps=None):
        return SimpleNamespace(timestamp=timestamp, quadrants=tuple(quadrants) if quadrants else (0, 1, 2, 3))

    def detect_slice(self, points, slice_index, timestamp=None):
        return SimpleNamespace(slice_index=slice_index)
