"""The synthetic world's per-pixel masks, ``<image>.mask.npz`` beside each camera image: the one definition of the
format, written by ``data/synth_writer.py`` and read by image pretraining (``training/image_pretrain.py``) and the
LUT coverage study (``benchmarks/lut_coverage.py``).

A numpy ``savez_compressed`` file at the image's resolution with the members (``MASK_MEMBERS``):

    class_id      (H, W) uint8   index into CLASS_NAMES of the annotated object seen there, MASK_NONE (255)
                                 where none (ground, sky, buildings, the unannotated look-alikes, and objects this key frame
                                 does not annotate: those beyond ``annotation_range_m``)
    instance      (H, W) uint16  1 + the object's number in its scene, 0 where none; one object keeps its number
                                 in every camera and key frame of the scene
    ids           (M,) uint16    the instance numbers present in this image
    tokens        (M,) str       their nuScenes instance tokens (the ``instance`` table; each has a
                                 ``sample_annotation`` in this key frame), in the order of ``ids``
"""

from __future__ import annotations

import zipfile
import zlib
from pathlib import Path

import numpy as np

from streamdet.core.classes import NUM_CLASSES
from streamdet.core.errors import first_line
from streamdet.core.npz_input import NpyHeader, check_member_size, npy_header

MASK_SUFFIX = ".mask.npz"  # appended to the image's file name
MASK_NONE = 255  # class_id where no annotated object is
MASK_MEMBERS = ("class_id", "instance", "ids", "tokens")
# The most ids (instances) one mask may list: the writer stores instance ids as uint16, and a token is a short hash.
# With the maps tied to the image's (H, W), these bound what a load can allocate.
MAX_MASK_IDS = 1 << 16
MAX_MASK_TOKEN_CHARS = 256


def mask_path(image_path: str | Path) -> Path:
    """The mask file of the camera image at ``image_path``."""
    image_path = Path(image_path)
    return image_path.with_name(image_path.name + MASK_SUFFIX)


def write_mask(path: str | Path, class_id: np.ndarray, instance: np.ndarray, ids: np.ndarray, tokens: np.ndarray) -> Path:
    """A mask file at ``path`` from its members (see the module doc); returns ``path``."""
    path = Path(path)
    with open(path, "wb") as f:
        np.savez_compressed(f, class_id=np.asarray(class_id, np.uint8), instance=np.asarray(instance, np.uint16),
                            ids=np.asarray(ids, np.uint16), tokens=np.asarray(tokens, np.str_))  # fmt: skip
    return path


def read_mask(path: str | Path, height: int, width: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(class_id, instance, ids, tokens) of a ``<image>.mask.npz`` for an image of ``height`` x ``width`` pixels.

    Checked from the zip directory and the ``.npy`` headers before anything is inflated (as calibration/lut_file.py
    checks a lut.npz): a mask is an .npz from the dataset folder, and a small one can declare gigabytes. class_id and
    instance must be integer maps of exactly the image's (H, W), ids and tokens lists of equal length (at most
    MAX_MASK_IDS), each member exactly its header plus its data (not truncated or padded), no object (pickled) dtype.
    Then the contents: class ids 0..NUM_CLASSES-1 or MASK_NONE, instance and ids >= 0. Any failure is a one-line
    ValueError naming the file."""
    path = Path(path)
    try:
        with zipfile.ZipFile(path) as zf:
            names = [i.filename for i in zf.infolist()]
            repeated = sorted({n for n in names if names.count(n) > 1})
            missing = [m for m in MASK_MEMBERS if f"{m}.npy" not in names]
            if repeated or missing:
                raise ValueError(f"mask {path}: missing member(s) {missing}, repeated {repeated}; a mask holds {list(MASK_MEMBERS)}")
            infos = {m: zf.getinfo(f"{m}.npy") for m in MASK_MEMBERS}  # other members are never read
            headers = {m: npy_header(zf, infos[m]) for m in MASK_MEMBERS}  # core/npz_input.py
            _check_mask_headers(headers, infos, path, height, width)
            arrays = {}
            for m in MASK_MEMBERS:
                with zf.open(infos[m]) as f:
                    arrays[m] = np.lib.format.read_array(f, allow_pickle=False)  # bounded by the checked header
    except (OSError, EOFError, zipfile.BadZipFile, zipfile.LargeZipFile, zlib.error, KeyError) as e:
        raise ValueError(f"mask {path}: not a readable .npz: {first_line(e)}") from None
    except ValueError as e:
        msg = first_line(e)
        raise ValueError(msg if msg.startswith(f"mask {path}") else f"mask {path}: not a readable .npz: {msg}") from None
    class_id, instance, ids, tokens = (arrays[m] for m in MASK_MEMBERS)
    bad = (class_id < 0) | ((class_id >= NUM_CLASSES) & (class_id != MASK_NONE))
    if bad.any():
        raise ValueError(f"mask {path}: class_id {int(class_id[bad].flat[0])} at {int(bad.sum())} pixel(s); class ids are "
                         f"0..{NUM_CLASSES - 1} ({NUM_CLASSES} classes) or {MASK_NONE} (no object)")  # fmt: skip
    for name, arr in (("instance", instance), ("ids", ids)):
        if arr.size and arr.min() < 0:
            raise ValueError(f"mask {path}: {name} holds a negative id ({int(arr.min())})")
    return class_id, instance, ids, tokens


def _check_mask_headers(headers: dict[str, NpyHeader], infos: dict, path: Path, height: int, width: int) -> None:
    for m in ("class_id", "instance"):
        shape, dtype = headers[m].shape, headers[m].dtype
        if shape != (height, width) or dtype.kind not in "iu":
            raise ValueError(f"mask {path}: {m} must be an integer map of the image's shape ({height}, {width}), got "
                             f"{dtype} {shape}")  # fmt: skip
    ids_shape, ids_dtype = headers["ids"].shape, headers["ids"].dtype
    tok_shape, tok_dtype = headers["tokens"].shape, headers["tokens"].dtype
    if len(ids_shape) != 1 or ids_dtype.kind not in "iu" or ids_shape[0] > MAX_MASK_IDS:
        raise ValueError(f"mask {path}: ids must be a list of at most {MAX_MASK_IDS} integers, got {ids_dtype} {ids_shape}")
    if tok_shape != ids_shape or tok_dtype.kind != "U" or tok_dtype.itemsize > 4 * MAX_MASK_TOKEN_CHARS:
        raise ValueError(f"mask {path}: tokens must be {ids_shape[0]} strings (one per id) of at most {MAX_MASK_TOKEN_CHARS} "
                         f"characters, got {tok_dtype} {tok_shape}")  # fmt: skip
    for m in MASK_MEMBERS:
        check_member_size(infos[m], headers[m])  # the zip reader never inflates past it: this bounds the read
