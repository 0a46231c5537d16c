"""streamdet.core: the vocabulary every other package shares (numpy only; imports nothing else of streamdet).

- ``classes``: ``CLASS_NAMES`` (a label is an index into it)
- ``boxes``: the ``(N, 9)`` box layout and the box geometry (corners, rotated BEV IoU)
- ``points``: the sweep ``(N, 5)`` and slice ``(N, 6)`` point layouts
- ``sectors``: azimuth, quadrants and streaming sectors
- ``rotations``: quaternions (w, x, y, z), rotation matrices and yaw
- ``slicing``: ``split_sweep``, ``boxes_in_sector``, ``relative_time_s``
- ``constants``: the graph precisions and the ``bundled:`` sources
- ``cpu``: the CPU model and the SIMD flags the kernels see (less what a CPUID mask hides)
- ``json_input``: reading input JSON bounded and with named errors, the safe finite-number test, cut reprs
- ``npz_input``: an .npz member's header and size checked before anything inflates (LUTs, masks)
- ``file_output``: ``atomic_write_file``, a whole output file written atomically with a plain file's permissions
- ``file_input``: ``read_regular_file``, a whole input file read once, bounded (never a FIFO or a device)
- ``errors``: ``first_line``, an exception in one line (what CLIs and wrapping errors quote)
- ``image_header``: a JPEG's or PNG's size from its header, checked before anything decodes it (decompression bombs)
"""

from streamdet.core.boxes import BOX_DIM
from streamdet.core.classes import CLASS_NAMES, NUM_CLASSES
from streamdet.core.constants import BUNDLED_PREFIX, PRECISIONS
from streamdet.core.points import SLICE_COLUMNS, SWEEP_COLUMNS, SWEEP_DURATION_S
from streamdet.core.sectors import NUM_QUADRANTS, check_num_slices
from streamdet.core.slicing import boxes_in_sector, split_sweep

__all__ = [
    "BOX_DIM",
    "BUNDLED_PREFIX",
    "CLASS_NAMES",
    "NUM_CLASSES",
    "NUM_QUADRANTS",
    "PRECISIONS",
    "SLICE_COLUMNS",
    "SWEEP_COLUMNS",
    "SWEEP_DURATION_S",
    "boxes_in_sector",
    "check_num_slices",
    "split_sweep",
]
