"""sensor_msgs/Image and CompressedImage -> RGB, and every refusal's message."""

from __future__ import annotations

from types import SimpleNamespace as ns

import cv2
import numpy as np
import pytest

from streamdet.runtime_ort.ros.header import RosMessageError
from streamdet.runtime_ort.ros.images import (
    compressed_image_message,
    compressed_image_to_rgb,
    image_to_rgb,
    rgb_to_compressed_image_message,
)


def _rgb(seed: int, h: int = 7, w: int = 11) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 256, (h, w, 3), dtype=np.uint8)


def _raw(rgb: np.ndarray, encoding: str, pad: int = 0, kind: str = "bytes") -> ns:
    pixels = rgb[:, :, ::-1] if encoding == "bgr8" else rgb
    h, w, _ = rgb.shape
    rows = np.zeros((h, 3 * w + pad), np.uint8)
    rows[:, : 3 * w] = pixels.reshape(h, 3 * w)
    data = rows.tobytes() if kind == "bytes" else rows.reshape(-1)
    return ns(header=ns(frame_id="cam"), height=h, width=w, encoding=encoding, is_bigendian=0, step=3 * w + pad, data=data)


@pytest.mark.parametrize("encoding", ["rgb8", "bgr8"])
@pytest.mark.parametrize("pad", [0, 5])
@pytest.mark.parametrize("kind", ["bytes", "numpy"])
@pytest.mark.parametrize("seed", [0, 1])
def test_raw_colour_images(encoding: str, pad: int, kind: str, seed: int):
    rgb = _rgb(seed)
    out = image_to_rgb(_raw(rgb, encoding, pad, kind))
    assert out.dtype == np.uint8 and out.flags.c_contiguous
    np.testing.assert_array_equal(out, rgb)


@pytest.mark.parametrize("encoding", ["mono8", "mono16", "bayer_rggb8", "16UC1", "32FC1", "8UC4", "yuv422"])
def test_other_raw_encodings_are_refused_by_name(encoding: str):
    msg = _raw(_rgb(0), "rgb8")
    msg.encoding = encoding
    with pytest.raises(RosMessageError, match=f"encoding '{encoding}' is not supported: streamdet takes colour images in "
                       "rgb8, bgr8, rgba8, bgra8"):  # fmt: skip
        image_to_rgb(msg)


def test_malformed_raw_images():
    msg = _raw(_rgb(0), "rgb8")
    msg.step = 10
    with pytest.raises(ValueError, match="step 10 < 3 x width 11"):
        image_to_rgb(msg)
    msg = _raw(_rgb(0), "rgb8")
    msg.data = msg.data[:-1]
    with pytest.raises(ValueError, match="data holds 230 bytes; 7 rows of step 33 need 231"):
        image_to_rgb(msg)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_jpeg_within_jpeg_error_and_png_exact(seed: int):
    rgb = cv2.GaussianBlur(_rgb(seed, 48, 64), (0, 0), 4)  # smooth, as camera images are
    jpeg = rgb_to_compressed_image_message(rgb, 5, "cam", quality=95)
    assert jpeg["format"] == "jpeg" and jpeg["header"]["stamp"] == {"sec": 0, "nanosec": 5}
    out = compressed_image_to_rgb(ns(**jpeg))
    assert out.shape == rgb.shape and out.dtype == np.uint8
    assert np.abs(out.astype(int) - rgb.astype(int)).mean() < 2.0
    ok, png = cv2.imencode(".png", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    for fmt in ("png", "rgb8; png compressed bgr8"):
        np.testing.assert_array_equal(compressed_image_to_rgb(ns(**compressed_image_message(png.tobytes(), 0, "cam", fmt))), rgb)
    np.testing.assert_array_equal(compressed_image_to_rgb(ns(format="png", data=png.reshape(-1))), rgb)  # numpy payload


def test_compressed_refusals_name_the_format():
    rgb = _rgb(0, 16, 16)
    ok, jpg = cv2.imencode(".jpg", rgb)
    for fmt in ("h264", "qoi", "mono8; jpeg compressed mono8", "16UC1; compressedDepth png"):
        with pytest.raises(ValueError, match=f"format '{fmt}' is not supported: streamdet takes colour jpeg or png"):
            compressed_image_to_rgb(ns(format=fmt, data=jpg.tobytes()))
    with pytest.raises(ValueError, match=r"\(jpeg\) holds no data"):
        compressed_image_to_rgb(ns(format="jpeg", data=b""))
    with pytest.raises(ValueError, match=r"\(jpeg, 9 bytes\) could not be decoded"):
        compressed_image_to_rgb(ns(format="jpeg", data=b"not a jpg"))
    ok, gray = cv2.imencode(".png", rgb[:, :, 0])
    with pytest.raises(RosMessageError, match=r"\(png\) is a single-channel \(grey\) 8-bit png image; streamdet takes 8-bit colour"):
        compressed_image_to_rgb(ns(format="png", data=gray.tobytes()))
    ok, deep = cv2.imencode(".png", (rgb.astype(np.uint16) * 200))
    with pytest.raises(RosMessageError, match=r"\(png\) is a 3-channel 16-bit png image; streamdet takes 8-bit colour"):
        compressed_image_to_rgb(ns(format="png", data=deep.tobytes()))
    with pytest.raises(ValueError, match=r"expected an \(H, W, 3\) uint8 RGB image"):
        rgb_to_compressed_image_message(rgb[:, :, 0], 0, "cam")
