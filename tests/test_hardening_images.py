"""Hostile camera images (audit part 2, findings 2, 3, 8 and 9): decompression bombs refused from the header before
decoding, OpenCV errors as ValueErrors naming the input, FIFOs / folders / devices named like images, truncated
JPEGs, grey and 16-bit images, and images whose size differs from their camera's calibration."""

from __future__ import annotations

import os
import struct
import zlib
from pathlib import Path
from types import SimpleNamespace as ns

import cv2
import numpy as np
import pytest

from streamdet.bag import run as bag_run
from streamdet.calibration.camera import MAX_IMAGE_PX
from streamdet.core import image_header as ih
from streamdet.core.image_header import (
    MAX_IMAGE_PIXELS,
    MAX_IMAGE_SIDE_PX,
    check_image_header,
    read_image_header,
)
from streamdet.data import sample as sample_mod
from streamdet.data.sample import ImageFileError, load_image
from streamdet.runtime_ort.ros import images as ros_images
from streamdet.runtime_ort.ros.images import compressed_image_to_rgb, image_to_rgb


def _bgr(h: int = 12, w: int = 20, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 256, (h, w, 3), dtype=np.uint8)


def _encode(ext: str, image: np.ndarray, params: list[int] | None = None) -> bytes:
    ok, buf = cv2.imencode(ext, image, params or [])
    assert ok
    return buf.tobytes()


def _png_with_size(w: int, h: int) -> bytes:
    """A valid small PNG whose IHDR is patched to declare ``w`` x ``h`` (CRC fixed, so only the size lies)."""
    b = bytearray(_encode(".png", _bgr(4, 4)))
    b[16:24] = struct.pack(">II", w, h)
    b[29:33] = struct.pack(">I", zlib.crc32(bytes(b[12:29])) & 0xFFFFFFFF)
    return bytes(b)


def _jpeg_with_size(w: int, h: int, progressive: bool = False) -> bytes:
    """A valid small JPEG whose SOFn is patched to declare ``w`` x ``h`` (the scan data then ends almost at once)."""
    params = [cv2.IMWRITE_JPEG_PROGRESSIVE, 1] if progressive else []
    b = bytearray(_encode(".jpg", np.full((16, 16, 3), 128, np.uint8), params))
    i = 2
    while True:
        marker, length = b[i + 1], struct.unpack(">H", b[i + 2 : i + 4])[0]
        if marker in (0xC0, 0xC1, 0xC2):
            b[i + 5 : i + 9] = struct.pack(">HH", h, w)
            return bytes(b)
        i += 2 + length


def _msg(data: bytes, fmt: str = "jpeg", stamp_ns: int = 1_500_000_000_123) -> ns:
    sec, nanosec = divmod(stamp_ns, 10**9)
    return ns(format=fmt, data=data, header=ns(stamp=ns(sec=sec, nanosec=nanosec), frame_id="cam"))


@pytest.fixture
def no_decode(monkeypatch):
    """Fail the test if anything is decoded: a bomb must be refused from its header."""

    def boom(*a, **k):
        raise AssertionError("cv2.imdecode called on an image that should have been refused from its header")

    monkeypatch.setattr(cv2, "imdecode", boom)
    monkeypatch.setattr(cv2, "imread", boom)


# ---- the header parser -------------------------------------------------------------------------------------------


def test_one_limit_for_every_reader_matches_the_calibration_limit():
    assert MAX_IMAGE_SIDE_PX == MAX_IMAGE_PX  # core cannot import calibration; this ties the two
    assert MAX_IMAGE_PIXELS == 64 << 20 and 1600 * 900 < MAX_IMAGE_PIXELS


@pytest.mark.parametrize("ext, params, fmt", [
    (".jpg", [], "jpeg"),
    (".jpg", [cv2.IMWRITE_JPEG_PROGRESSIVE, 1], "jpeg"),  # SOF2
    (".jpg", [cv2.IMWRITE_JPEG_OPTIMIZE, 1], "jpeg"),
    (".png", [], "png"),
])  # fmt: skip
@pytest.mark.parametrize("h, w", [(1, 1), (12, 20), (37, 5)])
def test_header_reads_the_size_of_real_images(ext, params, fmt, h, w):
    header = read_image_header(_encode(ext, _bgr(h, w), params))
    assert (header.format, header.width, header.height, header.channels, header.bit_depth) == (fmt, w, h, 3, 8)
    assert header.is_colour_8bit


def test_header_skips_app_segments_and_fill_bytes():
    jpg = _encode(".jpg", _bgr(9, 7))
    app = b"\xff\xe1" + struct.pack(">H", 2 + 1000) + b"Exif\0\0" + b"\0" * 994  # a 1 kB EXIF-like APP1
    header = read_image_header(jpg[:2] + b"\xff\xff\xff" + app + jpg[2:])
    assert (header.width, header.height) == (7, 9)
    assert read_image_header(np.frombuffer(jpg, np.uint8)).width == 7  # a numpy payload, as ROS gives


@pytest.mark.parametrize("data, match", [
    (b"", "is empty"),
    (b"BM" + b"\0" * 60, "not a JPEG or PNG"),
    (b"II*\0" + b"\0" * 60, "not a JPEG or PNG"),  # TIFF
    (b"P6\n60000 60000\n255\n", "not a JPEG or PNG"),  # PPM
    (b"\xff\xd8", "ends .* before its frame header"),
    (b"\xff\xd8\xff", "ends .* before its frame header"),
    (b"\xff\xd8\xff\xe0\x00", "cut short"),
    (b"\xff\xd8\xff\xe0\x00\x01", "length 1"),
    (b"\xff\xd8\x00\x00", "no marker at byte 2"),
    (b"\xff\xd8\xff\xda\x00\x08", "marker 0xFFDA"),  # the scan before any frame header
    (b"\xff\xd8\xff\xd9", "marker 0xFFD9"),
    (b"\xff\xd8\xff\xc0\x00\x11\x08\x00", "cut short in its frame header"),
    (b"\xff\xd8" + b"\xff" * (ih._JPEG_MAX_FILL + 2), "fill bytes"),
    (b"\xff\xd8" + b"\xff\xfe\x00\x02" * (ih._JPEG_MAX_SEGMENTS + 1), "no frame header in its first"),
    (b"\x89PNG\r\n\x1a\n\x00\x00", "PNG cut short"),
    (b"\x89PNG\r\n\x1a\n" + struct.pack(">I4s", 13, b"IDAT") + b"\0" * 17, "not a 13-byte IHDR"),
    (b"\x89PNG\r\n\x1a\n" + struct.pack(">I4sIIBB", 13, b"IHDR", 4, 4, 8, 5) + b"\0" * 7, "colour type 5"),
])  # fmt: skip
def test_header_refuses_malformed_data(data, match):
    with pytest.raises(ValueError, match=match):
        read_image_header(data)


@pytest.mark.parametrize("make", [_png_with_size, _jpeg_with_size, lambda w, h: _jpeg_with_size(w, h, True)])
@pytest.mark.parametrize("w, h, ok", [
    (30000, 30000, False), (65000, 65000, False), (60000, 60000, False),
    (65535, 1024, True), (MAX_IMAGE_SIDE_PX, 1, True), (MAX_IMAGE_SIDE_PX + 1, 1, False),
    (8192, 8192, True), (8192, 8193, False), (0, 10, False), (10, 0, False),
])  # fmt: skip
def test_size_limits(make, w, h, ok):
    if make is _png_with_size or w <= 65535 and h <= 65535:  # JPEG sides are 16-bit
        data = make(w, h)
        if ok:
            assert (check_image_header(data, "x").width, check_image_header(data, "x").height) == (w, h)
        else:
            with pytest.raises(ValueError, match=rf"^x declares {w}x{h} px"):
                check_image_header(data, "x")


# ---- finding 2: decompression bombs, refused before decoding ------------------------------------------------------


BOMBS = {
    "jpeg_30000.jpg": lambda: _jpeg_with_size(30000, 30000),
    "jpeg_65000x16000.jpg": lambda: _jpeg_with_size(65000, 16000),
    "progressive_20000.jpg": lambda: _jpeg_with_size(20000, 20000, progressive=True),
    "png_30000.png": lambda: _png_with_size(30000, 30000),
    "png_60000.png": lambda: _png_with_size(60000, 60000),
    "png_2e9.png": lambda: _png_with_size(2**31 - 1, 2**31 - 1),
    "png_as.jpg": lambda: _png_with_size(20000, 20000),  # a PNG under a .jpg name
}


@pytest.mark.parametrize("name", sorted(BOMBS))
def test_load_image_refuses_bombs_from_the_header(tmp_path, no_decode, name):
    path = tmp_path / name
    path.write_bytes(BOMBS[name]())
    with pytest.raises(ValueError, match=rf"image {path} declares \d+x\d+ px .*refused before decoding"):
        load_image(path, (384, 216))


@pytest.mark.parametrize("name", sorted(BOMBS))
def test_compressed_image_refuses_bombs_from_the_header(no_decode, name):
    fmt = "png" if "png" in name else "jpeg"
    with pytest.raises(ValueError, match=r"CompressedImage \((jpeg|png)\) at stamp 1500000000123 ns declares \d+x\d+ px"):
        compressed_image_to_rgb(_msg(BOMBS[name](), fmt))


def test_files_over_the_byte_limit_are_refused_before_reading(tmp_path, monkeypatch):
    path = tmp_path / "big.jpg"
    path.write_bytes(_encode(".jpg", _bgr()))
    monkeypatch.setattr(sample_mod, "MAX_IMAGE_FILE_BYTES", 100)
    with pytest.raises(ValueError, match=rf"image {path} is \d+ bytes, over"):
        load_image(path)
    monkeypatch.setattr(ros_images, "MAX_IMAGE_FILE_BYTES", 100)
    with pytest.raises(ValueError, match=r"holds \d+ bytes, over"):
        compressed_image_to_rgb(_msg(path.read_bytes()))


# ---- finding 3: cv2.error and empty raw images become ValueErrors naming the input --------------------------------


def _cv2_error(*a, **k):
    raise cv2.error("OpenCV(4.x) /src/alloc.cpp:73: error: (-4:Insufficient memory) Failed to allocate 2700000000 bytes")


def test_cv2_errors_while_decoding_are_value_errors(tmp_path, monkeypatch):
    path = tmp_path / "a.jpg"
    path.write_bytes(_encode(".jpg", _bgr()))
    monkeypatch.setattr(cv2, "imdecode", _cv2_error)
    with pytest.raises(ValueError, match=rf"image {path} \(20x12 jpeg\) could not be decoded: .*Insufficient memory"):
        load_image(path)
    with pytest.raises(ValueError, match=r"CompressedImage \(jpeg, \d+ bytes\) at stamp \d+ ns could not be decoded .*Failed to allocate"):
        compressed_image_to_rgb(_msg(path.read_bytes()))


def test_cv2_errors_while_resizing_are_value_errors(tmp_path, monkeypatch):
    path = tmp_path / "a.png"
    path.write_bytes(_encode(".png", _bgr()))
    monkeypatch.setattr(cv2, "resize", _cv2_error)
    with pytest.raises(ValueError, match=rf"image {path}: cannot resize .*Insufficient memory"):
        load_image(path, (8, 8))
    with pytest.raises(ValueError, match=r"camera CAM_FRONT: image at stamp 7 ns \(20x12 px\) cannot be resized to 8x8: .*Insufficient"):
        bag_run._resized(_bgr()[:, :, ::-1].copy(), (8, 8), "CAM_FRONT", 7)


def _raw(w: int, h: int, data: bytes = b"", encoding: str = "rgb8") -> ns:
    return ns(encoding=encoding, width=w, height=h, step=3 * w, data=data,
              header=ns(stamp=ns(sec=3, nanosec=4), frame_id="cam"))  # fmt: skip


@pytest.mark.parametrize("w, h", [(0, 0), (0, 900), (1600, 0), (-1, 5)])
def test_raw_image_without_pixels_is_refused(w, h):
    with pytest.raises(ValueError, match=rf"sensor_msgs/Image at stamp 3000000004 ns has no pixels \({w}x{h}\)"):
        image_to_rgb(_raw(w, h))


@pytest.mark.parametrize("w, h", [(MAX_IMAGE_SIDE_PX + 1, 1), (10000, 10000), (2**32 - 1, 2**32 - 1)])
def test_raw_image_over_the_limit_is_refused(w, h):
    with pytest.raises(ValueError, match=rf"is {w}x{h} px, over the image limit"):
        image_to_rgb(_raw(w, h, b"\0" * 10))


@pytest.mark.parametrize("shape", [(0, 0, 3), (0, 5, 3), (5, 0, 3), (5, 5), (5, 5, 1)])
def test_bag_resize_refuses_empty_or_non_colour_arrays(shape):
    with pytest.raises(ValueError, match=r"camera CAM_FRONT: image at stamp 9 ns is .*not a non-empty \(H, W, 3\) image"):
        bag_run._resized(np.zeros(shape, np.uint8), (384, 216), "CAM_FRONT", 9)


# ---- finding 9: FIFOs, folders and devices named like images --------------------------------------------------------



@pytest.mark.parametrize("kind", ["fifo", "dir", "device", "missing", "dangling_link"])
def test_non_regular_files_are_refused_without_blocking(tmp_path, alarm, kind):
    path = tmp_path / "CAM_FRONT.jpg"
    if kind == "fifo":
        os.mkfifo(path)
    elif kind == "dir":
        path.mkdir()
    elif kind == "device":
        if not Path("/dev/zero").exists():
            pytest.skip("no /dev/zero")
        path.symlink_to("/dev/zero")
    elif kind == "dangling_link":
        path.symlink_to(tmp_path / "nowhere.jpg")
    with pytest.raises(ImageFileError, match=rf"cannot read image {path}: (missing|not a regular file)"):
        load_image(path)
    assert issubclass(ImageFileError, ValueError) and issubclass(ImageFileError, FileNotFoundError)


# ---- finding 8: truncated, grey, 16-bit and wrong-size images -----------------------------------------------------


def _smooth(h: int = 90, w: int = 160) -> np.ndarray:
    return cv2.GaussianBlur(_bgr(h, w, 3), (0, 0), 3)


@pytest.mark.parametrize("keep", [0.3, 0.5, 0.9])
def test_truncated_jpeg_is_refused_not_filled_grey(tmp_path, keep):
    jpg = _encode(".jpg", _smooth())
    path = tmp_path / "trunc.jpg"
    path.write_bytes(jpg[: int(len(jpg) * keep)])
    with pytest.raises(ImageFileError, match=rf"cannot read image {path}: not a decodable image \(jpeg declaring 160x90 px; truncated"):
        load_image(path)
    with pytest.raises(ValueError, match=r"could not be decoded \(truncated or corrupt jpeg\)"):
        compressed_image_to_rgb(_msg(path.read_bytes()))


@pytest.mark.parametrize("cut", [1, 10, 100, 300])
def test_image_cut_in_its_header_is_refused(tmp_path, cut):
    for ext in (".jpg", ".png"):
        path = tmp_path / f"head{ext}"
        path.write_bytes(_encode(ext, _smooth())[:cut])
        with pytest.raises(ImageFileError, match=rf"cannot read image {path}"):
            load_image(path)


@pytest.mark.parametrize("name, make, what", [
    ("gray.png", lambda: _encode(".png", _smooth()[:, :, 0]), "single-channel \\(grey\\) 8-bit png"),
    ("gray.jpg", lambda: _encode(".jpg", _smooth()[:, :, 0]), "single-channel \\(grey\\) 8-bit jpeg"),
    ("gray16.png", lambda: _encode(".png", _smooth()[:, :, 0].astype(np.uint16) * 257), "single-channel \\(grey\\) 16-bit png"),
    ("rgb16.png", lambda: _encode(".png", _smooth().astype(np.uint16) * 257), "3-channel 16-bit png"),
    ("ga.png", lambda: _png_grey_alpha(), "grey\\+alpha 8-bit png"),
])  # fmt: skip
def test_non_colour_images_are_refused_by_load_image(tmp_path, name, make, what):
    path = tmp_path / name
    path.write_bytes(make())
    with pytest.raises(ValueError, match=rf"image {path} is a {what} image; streamdet takes 8-bit colour"):
        load_image(path)


def _png_grey_alpha() -> bytes:
    raw = b"".join(b"\0" + bytes([100, 255]) * 4 for _ in range(4))
    ihdr = struct.pack(">IIBBBBB", 4, 4, 8, 4, 0, 0, 0)

    def chunk(t: bytes, d: bytes) -> bytes:
        return struct.pack(">I", len(d)) + t + d + struct.pack(">I", zlib.crc32(t + d) & 0xFFFFFFFF)

    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(raw)) + chunk(b"IEND", b"")


def test_colour_images_still_load_as_before(tmp_path):
    bgr = _smooth()
    for ext in (".jpg", ".png"):
        path = tmp_path / f"c{ext}"
        path.write_bytes(_encode(ext, bgr))
        expected = cv2.cvtColor(cv2.imread(str(path), cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)
        np.testing.assert_array_equal(load_image(path), expected)
        resized = cv2.cvtColor(cv2.resize(cv2.imread(str(path)), (40, 30), interpolation=cv2.INTER_AREA), cv2.COLOR_BGR2RGB)
        np.testing.assert_array_equal(load_image(path, (40, 30)), resized)
    rgba = np.dstack([bgr, np.full(bgr.shape[:2], 7, np.uint8)])
    path = tmp_path / "rgba.png"
    path.write_bytes(_encode(".png", rgba))
    np.testing.assert_array_equal(load_image(path), bgr[:, :, ::-1])  # alpha dropped


@pytest.mark.parametrize("data", [
    _encode(".bmp", _bgr()), _encode(".ppm", _bgr()), _encode(".tiff", _bgr()), b"P6\n60000 60000\n255\n",
])  # fmt: skip
def test_formats_other_than_jpeg_and_png_are_refused(tmp_path, no_decode, data):
    path = tmp_path / "other.jpg"
    path.write_bytes(data)
    with pytest.raises(ImageFileError, match=rf"cannot read image {path}: it is not a JPEG or PNG image"):
        load_image(path)
    with pytest.raises(ValueError, match=r"could not be decoded: the data is not a JPEG or PNG image"):
        compressed_image_to_rgb(_msg(data))


@pytest.mark.parametrize("expected, ok", [((160, 90), True), ((1600, 900), False), ((90, 160), False), ((1, 1), False)])
def test_load_image_expected_size(tmp_path, expected, ok):
    path = tmp_path / "cam.jpg"
    path.write_bytes(_encode(".jpg", _smooth()))
    if ok:
        assert load_image(path, (32, 18), expected_size=expected).shape == (18, 32, 3)
    else:
        with pytest.raises(ValueError, match=rf"image {path} is 160x90 px but its camera is calibrated for {expected[0]}x{expected[1]}"):
            load_image(path, expected_size=expected)
    with pytest.raises(ValueError, match="size must be positive"):
        load_image(path, expected_size=(0, 9))


def _event(images: dict, sizes: dict | None) -> ns:
    rig = None if sizes is None else ns(cameras=tuple(ns(name=n, width=w, height=h) for n, (w, h) in sizes.items()))
    return ns(image_set=ns(rig=rig, images=images, stamps_ns={n: 11 for n in images}, stamp_ns=11))


@pytest.mark.parametrize("shape", [(900, 64, 3), (1, 1, 3), (1600, 900, 3)])
def test_bag_images_must_match_their_camera_info(shape):
    event = _event({"CAM_FRONT": np.zeros(shape, np.uint8)}, {"CAM_FRONT": (1600, 900)})
    with pytest.raises(ValueError, match=rf"camera CAM_FRONT: image at stamp 11 ns is {shape[1]}x{shape[0]} px but its CameraInfo is for 1600x900"):
        bag_run._feed_images(None, event)  # refused before the detector is touched


def test_bag_images_matching_their_camera_info_are_fed():
    fed = {}
    det = ns(lut=ns(calibration_sha256="same"), image=ns(width=16, height=9),
             update_images=lambda images, timestamp: fed.update(images))  # fmt: skip
    event = _event({"CAM_FRONT": np.zeros((900, 1600, 3), np.uint8)}, {"CAM_FRONT": (1600, 900)})
    event.image_set.rig.sha256 = lambda: "same"
    bag_run._feed_images(det, event)
    assert fed["CAM_FRONT"].shape == (9, 16, 3)
    bag_run._feed_images(det, _event({"CAM_FRONT": np.zeros((90, 160, 3), np.uint8)}, None))  # no CameraInfo: no check
    assert fed["CAM_FRONT"].shape == (9, 16, 3)


def _jpeg_with_exif_orientation(image: np.ndarray, orientation: int) -> bytes:
    """A JPEG of ``image`` carrying an APP1 Exif segment whose IFD0 sets Orientation (0x0112)."""
    jpg = _encode(".jpg", image)
    tiff = b"II*\x00" + struct.pack("<IH", 8, 1) + struct.pack("<HHII", 0x0112, 3, 1, orientation) + struct.pack("<I", 0)
    app1 = b"Exif\x00\x00" + tiff
    return jpg[:2] + b"\xff\xe1" + struct.pack(">H", len(app1) + 2) + app1 + jpg[2:]


@pytest.mark.parametrize("orientation", [1, 3, 6, 8])
def test_exif_orientation_is_ignored_pixels_as_stored(tmp_path, orientation):
    """The camera's K is for the stored pixel grid: a rotation tag must not turn (or, resized, squash) the image."""
    bgr = _smooth()  # (90, 160, 3)
    data = _jpeg_with_exif_orientation(bgr, orientation)
    path = tmp_path / "rot.jpg"
    path.write_bytes(data)
    plain = cv2.imdecode(np.frombuffer(_encode(".jpg", bgr), np.uint8), cv2.IMREAD_COLOR)[:, :, ::-1]
    np.testing.assert_array_equal(load_image(path, expected_size=(160, 90)), plain)
    assert load_image(path, (32, 18)).shape == (18, 32, 3)
    np.testing.assert_array_equal(compressed_image_to_rgb(_msg(data)), plain)
