"""An encoded camera image's size and colour layout read from its header, before any pixel is decoded.

Every image reader (``data.sample.load_image``, ``runtime_ort.ros.images.compressed_image_to_rgb``) checks the
bytes here first: a few hundred bytes of JPEG or PNG can declare 30000x30000 px, and a decoder allocates the full
image (2.7 GB as BGR) before it finds the data missing. Only JPEG and PNG are taken (what cameras, nuScenes and the
synthetic data write); any other format OpenCV would decode is refused rather than handed to a decoder whose
header nothing here checks.

Limits: ``MAX_IMAGE_SIDE_PX`` (65536, the same as ``calibration.camera.MAX_IMAGE_PX``, the largest side any
camera may be calibrated for) per side and ``MAX_IMAGE_PIXELS`` (64 Mpx: 8192x8192, 46 nuScenes 1600x900 frames;
192 MiB as 8-bit BGR) in all; ``MAX_IMAGE_FILE_BYTES`` (256 MiB) for the encoded file. Pure Python (core is
numpy-only and torch-free).
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from typing import Any

MAX_IMAGE_SIDE_PX = 65536  # == calibration.camera.MAX_IMAGE_PX (core imports nothing of streamdet; a test ties them)
MAX_IMAGE_PIXELS = 64 << 20  # 67,108,864 px; a nuScenes frame is 1600x900 = 1.44 Mpx
MAX_IMAGE_FILE_BYTES = 256 << 20  # an encoded image larger than this is refused before it is read

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
JPEG_SOI = b"\xff\xd8"
# SOF0..SOF15 less DHT (C4), JPG (C8) and DAC (CC): the frame header that holds the size
_JPEG_SOF = frozenset(range(0xC0, 0xD0)) - {0xC4, 0xC8, 0xCC}
_JPEG_STANDALONE = frozenset(range(0xD0, 0xD8)) | {0x01}  # RSTn and TEM carry no length
_JPEG_MAX_SEGMENTS = 4096  # segments before the frame header (APPn, DQT, ...); real files have ~10
_JPEG_MAX_FILL = 1 << 16
_PNG_COLOUR_CHANNELS = {0: 1, 2: 3, 3: 3, 4: 2, 6: 4}  # colour type -> channels as decoded (palette: RGB)


@dataclass(frozen=True)
class ImageHeader:
    format: str  # "jpeg" or "png"
    width: int
    height: int
    channels: int  # JPEG: components (1 grey, 3 YCbCr/RGB, 4 CMYK); PNG: 1 grey, 2 grey+alpha, 3 RGB/palette, 4 RGBA
    bit_depth: int  # bits per sample: JPEG precision (8 or 12), PNG bit depth

    @property
    def is_colour_8bit(self) -> bool:
        """Colour with 8-bit samples (a palette PNG's 1-8-bit indices too): what the detector was trained on."""
        return self.channels >= 3 and self.bit_depth <= 8

    def describe(self) -> str:
        """E.g. "single-channel (grey) 16-bit png", for error messages."""
        kind = {1: "single-channel (grey)", 2: "grey+alpha"}.get(self.channels, f"{self.channels}-channel")
        return f"{kind} {self.bit_depth}-bit {self.format}"


def read_image_header(data: Any) -> ImageHeader:
    """The ``ImageHeader`` of encoded JPEG or PNG bytes (bytes, bytearray, memoryview or a uint8 array).

    ValueError (without a name: callers prefix the file or message) for any other format, or a header that is cut
    short or malformed. Reads only the header: the pixel data is not looked at.
    """
    buf = memoryview(data)
    if buf.ndim != 1 or buf.itemsize != 1:
        buf = buf.cast("B")
    if bytes(buf[:8]) == PNG_SIGNATURE:
        return _png_header(buf)
    if bytes(buf[:2]) == JPEG_SOI:
        return _jpeg_header(buf)
    head = bytes(buf[:8])
    if not head:
        raise ValueError("is empty (0 bytes)")
    raise ValueError(f"is not a JPEG or PNG image (starts with {head!r}); streamdet reads JPEG and PNG only")


def check_image_header(data: Any, where: str) -> ImageHeader:
    """``read_image_header`` plus ``check_image_size``; every ValueError starts with ``where`` (the file, the message)."""
    try:
        header = read_image_header(data)
    except ValueError as e:
        raise ValueError(f"{where} {e}") from None
    return check_image_size(header, where)


def check_image_size(header: ImageHeader, where: str) -> ImageHeader:
    """``header`` if its size is at least 1x1 and within ``MAX_IMAGE_SIDE_PX`` and ``MAX_IMAGE_PIXELS``."""
    w, h = header.width, header.height
    if w <= 0 or h <= 0:
        raise ValueError(f"{where} declares {w}x{h} px ({header.format}): an image needs at least one pixel")
    if w > MAX_IMAGE_SIDE_PX or h > MAX_IMAGE_SIDE_PX or w * h > MAX_IMAGE_PIXELS:
        raise ValueError(
            f"{where} declares {w}x{h} px ({header.format}), over the image limit of {MAX_IMAGE_SIDE_PX} px a side "
            f"and {MAX_IMAGE_PIXELS} px ({MAX_IMAGE_PIXELS >> 20} Mpx) in all; refused before decoding"
        )
    return header


def _png_header(buf: memoryview) -> ImageHeader:
    # signature (8), then the IHDR chunk: length (4) = 13, type "IHDR", width, height, bit depth, colour type, ...
    if len(buf) < 8 + 8 + 13:
        raise ValueError(f"is a PNG cut short in its header ({len(buf)} bytes)")
    length, kind = struct.unpack(">I4s", bytes(buf[8:16]))
    if kind != b"IHDR" or length != 13:
        raise ValueError("is a malformed PNG: its first chunk is not a 13-byte IHDR")
    width, height, depth, colour = struct.unpack(">IIBB", bytes(buf[16:26]))
    if colour not in _PNG_COLOUR_CHANNELS or depth not in (1, 2, 4, 8, 16):
        raise ValueError(f"is a malformed PNG: colour type {colour}, bit depth {depth}")
    return ImageHeader("png", width, height, _PNG_COLOUR_CHANNELS[colour], depth)


def _jpeg_header(buf: memoryview) -> ImageHeader:
    n = len(buf)
    i = 2
    fill_left = _JPEG_MAX_FILL  # fill bytes over all markers: bounds the byte-by-byte loop on a hostile file
    for _ in range(_JPEG_MAX_SEGMENTS):
        if i >= n:
            raise ValueError(f"is a JPEG that ends ({n} bytes) before its frame header (SOF)")
        if buf[i] != 0xFF:
            raise ValueError(f"is a malformed JPEG: no marker at byte {i} before the frame header")
        while i < n and buf[i] == 0xFF:  # a marker may be preceded by fill bytes
            i += 1
            fill_left -= 1
            if fill_left < 0:
                raise ValueError(f"is a malformed JPEG: over {_JPEG_MAX_FILL} fill bytes (0xFF) before the frame header")
        if i >= n:
            raise ValueError(f"is a JPEG that ends ({n} bytes) before its frame header (SOF)")
        marker = buf[i]
        i += 1
        if marker in _JPEG_STANDALONE:
            continue
        if marker in (0xD8, 0xD9, 0xDA):  # SOI again, EOI or the scan itself before any frame header
            raise ValueError(f"is a malformed JPEG: marker 0xFF{marker:02X} at byte {i - 2} before the frame header")
        if i + 2 > n:
            raise ValueError(f"is a JPEG cut short in its header ({n} bytes)")
        (length,) = struct.unpack(">H", bytes(buf[i : i + 2]))
        if length < 2:
            raise ValueError(f"is a malformed JPEG: segment 0xFF{marker:02X} at byte {i - 2} has length {length}")
        if marker in _JPEG_SOF:
            if length < 8 or i + 8 > n:
                raise ValueError(f"is a JPEG cut short in its frame header ({n} bytes)")
            precision, height, width, components = struct.unpack(">BHHB", bytes(buf[i + 2 : i + 8]))
            return ImageHeader("jpeg", width, height, components, precision)
        i += length
    raise ValueError(f"is a malformed JPEG: no frame header in its first {_JPEG_MAX_SEGMENTS} segments")


def decoder_error_reason(e: BaseException) -> str:
    """The reason of a decoder's error (OpenCV's ``cv2.error``) in one line: its text spans lines and names OpenCV's
    source file, the last line says what failed."""
    text = str(e).strip().splitlines()
    return text[-1].strip() if text else type(e).__name__
