"""``sensor_msgs/Image`` and ``sensor_msgs/CompressedImage`` -> (H, W, 3) uint8 RGB, the image lane's input.

The detector was trained on colour images, so only colour encodings are taken: ``rgb8`` and ``bgr8`` raw images
(and ``rgba8`` / ``bgra8``, which simulators publish: the alpha channel is dropped), JPEG and PNG compressed ones. A
mono, Bayer, 16-bit or depth image, or a grey+alpha PNG, is refused with the encoding named rather than silently
replicated into three channels.

A compressed image's size is read from its JPEG / PNG header (``core.image_header``) and refused over
``MAX_IMAGE_SIDE_PX`` a side or ``MAX_IMAGE_PIXELS`` in all before it is decoded (a few hundred bytes can declare
30000x30000 px); data that is neither JPEG nor PNG is refused whatever ``format`` says. A raw image needs at least
one pixel and the same limits. Every refusal, OpenCV's errors included, is a ``RosMessageError`` (a ValueError)
naming the message (its stamp, where it has a header).
"""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np

from streamdet.core.image_header import (
    MAX_IMAGE_FILE_BYTES,
    MAX_IMAGE_PIXELS,
    MAX_IMAGE_SIDE_PX,
    check_image_size,
    decoder_error_reason,
    read_image_header,
)
from streamdet.runtime_ort.ros.header import RosMessageError, byte_view, header_msg, header_stamp_ns, is_integer, shown

RAW_ENCODINGS = ("rgb8", "bgr8", "rgba8", "bgra8")
_CHANNELS = {"rgb8": 3, "bgr8": 3, "rgba8": 4, "bgra8": 4}
COMPRESSED_FORMATS = ("jpeg", "jpg", "png")
_NOT_COLOUR = ("mono", "bayer", "16u", "16s", "32f", "compresseddepth", "8uc1", "16uc1", "32fc1")


def image_to_rgb(msg: Any) -> np.ndarray:
    """(H, W, 3) uint8 RGB of a raw ``sensor_msgs/Image`` in ``rgb8``, ``bgr8``, ``rgba8`` or ``bgra8`` (alpha
    dropped; row padding allowed)."""
    encoding = str(msg.encoding)
    if encoding.lower() not in RAW_ENCODINGS:
        raise RosMessageError(
            f"sensor_msgs/Image encoding {encoding!r} is not supported: streamdet takes colour images in "
            f"{', '.join(RAW_ENCODINGS)} (debayer or convert mono / 16-bit images before the detector)"
        )
    channels = _CHANNELS[encoding.lower()]
    for field in ("height", "width", "step"):  # int() would take 2.7 or '3', and raise its own errors for None, nan
        if not is_integer(getattr(msg, field)):
            raise RosMessageError(f"sensor_msgs/Image.{field} must be an integer, got {shown(getattr(msg, field))}")
    height, width, step = int(msg.height), int(msg.width), int(msg.step)  # sizes checked below, with their own words
    if width <= 0 or height <= 0:
        raise RosMessageError(f"sensor_msgs/Image{_at(msg)} has no pixels ({width}x{height})")
    if width > MAX_IMAGE_SIDE_PX or height > MAX_IMAGE_SIDE_PX or width * height > MAX_IMAGE_PIXELS:
        raise RosMessageError(f"sensor_msgs/Image{_at(msg)} is {width}x{height} px, over the image limit of "
                              f"{MAX_IMAGE_SIDE_PX} px a side and {MAX_IMAGE_PIXELS} px in all")  # fmt: skip
    if step < channels * width:
        raise RosMessageError(f"sensor_msgs/Image step {step} < {channels} x width {width} for {encoding}")
    data = byte_view(msg.data, "sensor_msgs/Image.data")
    if data.size < step * height:
        raise RosMessageError(f"sensor_msgs/Image data holds {data.size} bytes; {height} rows of step {step} need {step * height}")
    rows = data[: step * height].reshape(height, step)  # (H, step)
    image = rows[:, : channels * width].reshape(height, width, channels)[:, :, :3]  # (H, W, 3), alpha dropped
    if encoding.lower().startswith("bgr"):
        return np.ascontiguousarray(image[:, :, ::-1])
    return np.ascontiguousarray(image)


def compressed_image_to_rgb(msg: Any) -> np.ndarray:
    """(H, W, 3) uint8 RGB of a ``sensor_msgs/CompressedImage`` holding a colour JPEG or PNG."""
    fmt = str(msg.format)
    lowered = fmt.lower()
    if not any(f in lowered for f in COMPRESSED_FORMATS) or any(f in lowered for f in _NOT_COLOUR):
        raise RosMessageError(
            f"sensor_msgs/CompressedImage format {fmt!r} is not supported: streamdet takes colour "
            f"{' or '.join(('jpeg', 'png'))} images"
        )
    data = byte_view(msg.data, f"sensor_msgs/CompressedImage ({fmt}) data")
    what = f"sensor_msgs/CompressedImage ({fmt}){_at(msg)}"
    if data.size == 0:
        raise RosMessageError(f"sensor_msgs/CompressedImage ({fmt}) holds no data")
    if data.size > MAX_IMAGE_FILE_BYTES:
        raise RosMessageError(f"{what} holds {data.size} bytes, over the {MAX_IMAGE_FILE_BYTES >> 20} MiB limit of an encoded image")
    where = f"sensor_msgs/CompressedImage ({fmt}, {data.size} bytes){_at(msg)}"
    try:
        header = read_image_header(data)  # before decoding: the size it declares, and JPEG or PNG only
    except ValueError as e:
        raise RosMessageError(f"{where} could not be decoded: the data {e}") from None
    try:
        check_image_size(header, f"{what}")
    except ValueError as e:  # the shared check's plain ValueError, as a message error
        raise RosMessageError(str(e)) from None
    if not header.is_colour_8bit:  # OpenCV would expand grey+alpha to BGRA, which would pass as colour below
        raise RosMessageError(f"{what} is a {header.describe()} image; streamdet takes 8-bit colour")
    try:
        bgr = cv2.imdecode(data, cv2.IMREAD_UNCHANGED)
    except cv2.error as e:  # a failed allocation, or a limit of OpenCV's own
        raise RosMessageError(f"{where} could not be decoded ({header.width}x{header.height} {header.format}): "
                              f"{decoder_error_reason(e)}") from None  # fmt: skip
    if bgr is None:
        raise RosMessageError(f"{where} could not be decoded (truncated or corrupt {header.format})")
    if bgr.ndim != 3 or bgr.shape[2] not in (3, 4) or bgr.dtype != np.uint8:
        what = "single-channel" if bgr.ndim == 2 else f"{bgr.shape[2]}-channel {bgr.dtype}"
        raise RosMessageError(f"sensor_msgs/CompressedImage ({fmt}){_at(msg)} decodes to a {what} image; streamdet takes 8-bit colour")
    try:
        return cv2.cvtColor(bgr, cv2.COLOR_BGRA2RGB if bgr.shape[2] == 4 else cv2.COLOR_BGR2RGB)
    except cv2.error as e:
        raise RosMessageError(f"{where}: cannot convert {bgr.shape[1]}x{bgr.shape[0]} px to RGB: {decoder_error_reason(e)}") from None


def _at(msg: Any) -> str:
    """" at stamp N ns" where ``msg`` has a readable header stamp, else "" (bare test messages have none)."""
    try:
        return f" at stamp {header_stamp_ns(msg)} ns"
    except (AttributeError, TypeError, ValueError, OverflowError):
        return ""


def compressed_image_message(data: bytes, stamp_ns: int, frame_id: str, fmt: str = "jpeg") -> dict:
    """A ``sensor_msgs/CompressedImage`` dict of already encoded bytes (a camera's JPEG, kept bit for bit)."""
    return {"header": header_msg(stamp_ns, frame_id), "format": fmt, "data": bytes(data)}


def rgb_to_compressed_image_message(rgb: np.ndarray, stamp_ns: int, frame_id: str, quality: int = 92) -> dict:
    """A JPEG ``sensor_msgs/CompressedImage`` dict of an (H, W, 3) uint8 RGB image."""
    rgb = np.asarray(rgb)
    if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.dtype != np.uint8:
        raise ValueError(f"expected an (H, W, 3) uint8 RGB image, got {rgb.dtype} {rgb.shape}")
    ok, buf = cv2.imencode(".jpg", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    if not ok:
        raise ValueError("JPEG encoding failed")
    return compressed_image_message(buf.tobytes(), stamp_ns, frame_id)
