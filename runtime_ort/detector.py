"""The torch-free streaming detector: an export directory in, per-slice detections out.

Two lanes share one cached image BEV:

- the **image lane** (`update_images`) encodes the newest camera images and lifts them with the projection LUT
  into the image BEV of all four quadrants (the full update), or of the quadrants asked for from the cameras that
  see them (a per-quadrant update, what `lanes.StreamingRunner`'s phase-locked schedule runs), then swaps them into
  the cache, which holds each quadrant with its own timestamp;
- the **slice lane** (`detect_slice`) pillarises one LiDAR slice, reads the cached image BEV of the slice's
  quadrant(s), runs the slice graph and post-processes its decoded boxes.

Both methods are thread-safe and may run at the same time from different threads: onnxruntime releases the
GIL and each graph has its own session and thread pool, so a slice does not wait behind an image-encoder run.
`streamdet.runtime_ort.lanes.StreamingRunner` adds the worker threads, bounded queues and back-pressure.

A LiDAR-only export (manifest preset use_image false, the paper's streaming baseline) has the slice lane alone:
its slice graph takes the quadrant ids instead of an image BEV, and `update_images` / `set_calibration` raise
`NoImageLaneError` (`uses_images` tells the two kinds apart). One trained without the quadrant crop (preset
slice_crop false, `slice_crop` here) runs one map of the whole grid per slice and takes the pillar tensors alone.

Contracts (README, "Trust and failure model"; docs/trust.md):

- **Start-up** verifies everything before the first slice: the manifest against ``manifest.schema.json``, every
  file it names confined to the export directory and matching its sha256, each graph's real signature against
  the manifest and against what the runtime feeds (``signature.py``). Any defect is a ManifestError
  (``export_open.py`` opens and checks the export; the call-argument checks are ``call_checks.py``).
- **Timestamps** are labels in seconds: a finite real number (NaN, inf, a bool or a string raise ValueError) or
  None, which means ``time.monotonic()`` when the call starts. They may go backwards (a driver clock that steps);
  they never order anything: the newest image set is the one whose `update_images` call started last.
- **Image cache**: a newer image set is never replaced by an older one that finishes later, and a calibration
  swap re-lifts the newest set; an image set finished under the old calibration is lifted again under the new.
- **Refusals change nothing**: a bad slice, image set or calibration raises before any cached state is touched.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import os
import threading
import weakref
import time
import warnings
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np

from streamdet.calibration.camera import CalibrationError, Rig
from streamdet.calibration.lut import BlindCameraWarning, CameraMovedWarning, Lut, moved_cameras  # noqa: F401 (BlindCameraWarning: public here)
from streamdet.calibration.quadrant_lut import QuadrantLut
from streamdet.core.constants import PRECISIONS  # noqa: F401 (public here too)
from streamdet.core.points import (
    MAX_POINT_TIME_S, MAX_SLICE_INDEX, MAX_SLICE_POINTS, MAX_SWEEP_POINTS, REFLECTANCE_RANGE, SLICE_INDEX, check_sweep,
    slice_points_problem,
)
from streamdet.core.sectors import NUM_QUADRANTS, quadrants_of_sector
from streamdet.core.slicing import feature_index, split_sweep
from streamdet.runtime_ort.call_checks import call_timestamp, slice_count, slice_index_problem
# the public names of the runtime's API are importable from here too, where StreamingDetector lives
from streamdet.runtime_ort.camera_terms import CameraTerms
from streamdet.runtime_ort.coalesce import check_coalesced, split_by_slice
from streamdet.runtime_ort.detector_config import DetectorClosed, DetectorConfig, NoImageLaneError, lane_precision_label  # noqa: F401
from streamdet.runtime_ort.detector_results import ImageUpdate, SliceResult, SweepResult
from streamdet.runtime_ort.export_open import check_lut, executed_gmac, export_lut, no_image_lane, open_export, provider_options
from streamdet.runtime_ort.heap import release_free_memory
from streamdet.runtime_ort.fallback import CLOCKS_APART_S, FALLBACK_GRAPH, IMPLAUSIBLE_IMAGE_AGE_S, LidarFallback, needs_fallback
from streamdet.runtime_ort.image_cache import (  # noqa: F401 (check_camera_timestamps: public here too)
    ALL_QUADRANTS, ImageCache, QuadrantState, check_camera_timestamps, quadrant_states, quadrant_timestamp, select_maps,
    update_quadrants,
)
from streamdet.runtime_ort.manifest import GraphEntry, ImageSpec, Manifest, ManifestError  # noqa: F401 (ManifestError: public here)
from streamdet.runtime_ort.pillarize import pillarize
from streamdet.runtime_ort.postprocess import Detections, PostprocessConfig, SliceRun, aggregate_sweep, postprocess_slice, top_k_reached
from streamdet.runtime_ort.recording import Feeds, GraphRecording
from streamdet.runtime_ort.sessions import CPU_PROVIDER, GraphRunError, GraphSession, ProviderError  # noqa: F401 (ProviderError: public here)
from streamdet.runtime_ort.warm_up import warm_up

log = logging.getLogger(__name__)

# Calibration swaps one image update follows (each a lift again with the newest LUT) before it gives its images up: a
# caller swapping faster than one lift would otherwise keep the image lane lifting for ever.
MAX_RELIFTS_PER_UPDATE = 4


class StreamingDetector:
    """Runs an export of streamdet with onnxruntime. Thread-safe.

    ``manifest``: None reads and verifies ``export_dir/manifest.json`` (what every user does). The exporter passes
    the manifest of the export it is still staging (its files in ``export_dir``, manifest.json not written yet), so
    that its int8 calibration and pipeline parity run this detector (export/staged_detector.py); the graphs are
    still checked against it.
    """

    def __init__(self, export_dir: str | Path, config: DetectorConfig = DetectorConfig(), manifest: Manifest | None = None) -> None:
        self.export_dir = Path(export_dir)
        # every check of the export and the config, its sessions, LUT and per-camera lifts (export_open.py)
        opened = open_export(self.export_dir, config, manifest)
        self.config = config = opened.config  # with the export's NMS settings where the config named none
        self.manifest: Manifest = opened.manifest
        self.grid = opened.grid
        self.uses_images: bool = opened.uses_images  # False: LiDAR-only export, slice lane only
        # False: a LiDAR-only net without the quadrant crop, one whole-grid map per slice (calibration/slice_maps.py)
        self.slice_crop: bool = opened.slice_crop
        self.camera_names: tuple[str, ...] = opened.camera_names
        self.image: ImageSpec | None = opened.image  # what update_images takes; None for a LiDAR-only export
        self.num_slices = opened.num_slices
        self._max_points_per_pillar = opened.max_points_per_pillar
        self._max_pillars = opened.max_pillars
        self._post = opened.post
        # None for a LiDAR-only export: it has no image lane
        self.image_encoder, self.lifter, self.slice_head = opened.image_encoder, opened.lifter, opened.slice_head
        self.providers = opened.providers
        self._fallback: LidarFallback | None = opened.fallback
        self.stats = opened.stats
        self._sessions = opened.sessions
        self._graph_files = opened.graph_files  # for messages
        self._recordings: tuple[GraphRecording, ...] = ()  # open recording() blocks (swapped whole under _lock)
        # The manifest's MAC counts of the graphs in use; _executed_gmac scales them to each run's sizes for the stats.
        self._graph_entries = opened.graph_entries

        self._lock = threading.Lock()  # guards the swaps of _lut and _image; reads take a reference
        self._cap_lock = threading.Lock()  # slice workers count runs at the top-K cap at once
        self._runs_at_top_k = 0
        self._warned_out_of_range = False  # a slice dropped points with a feature out of range (logged once)
        self._warned_nonfinite_outputs = False  # a slice graph run gave NaN / inf rows (logged once)
        self._warned_clocks = False  # a slice's image age said its lanes' clocks differ (logged once)
        self._warned_slice_index = False  # a slice's index column was not its slice's feature (logged once)
        self._feature_indices: dict[tuple[int, int], int] = {}  # (k, n) -> feature_index in this scan layout
        # encode_images' maps by id (weakly): trusted as they are by update_images / prepare_terms (_check_encoded)
        self._own_maps: weakref.WeakValueDictionary[int, np.ndarray] = weakref.WeakValueDictionary()
        self._calibration_lock = threading.Lock()  # one calibration swap (and its re-lift) at a time
        # set_calibration calls started, and the newest of them whose LUT is in use (or that found its rig in use):
        # a swap started earlier that reaches the lock later installs nothing (the newest call wins, as image updates)
        self._calibration_seq = 0
        self._calibration_won = 0
        self._image_seq = 0  # update_images calls started (under _lock)
        # per quadrant: image sets of calls up to this seq were dropped there (forget_images): never installed there
        self._image_floor = [0] * NUM_QUADRANTS
        # per quadrant: whether its image BEV was last dropped because none of its cameras had a frame (an update given
        # none of them, or the phase-locked lane's cameras timed out): its slices then name them in cameras_missing.
        # Read only where the quadrant holds no image; a tuple swapped whole, so a slice reads it without the lock
        self._cameras_out: tuple[bool, ...] = (False,) * NUM_QUADRANTS
        self._out_said = [0] * NUM_QUADRANTS  # per quadrant: the seq of the call that set _cameras_out there (_lock)
        self._lut: Lut | None = opened.lut  # stays None for a LiDAR-only export
        self._built_from: tuple[Lut, str] | None = opened.built_from  # (a LUT this detector built, its rig's sha256): _is_current_rig
        self._image: ImageCache | None = None  # None before the first image update; replaced whole under _lock
        self._blank_bev: np.ndarray | None = None  # blank_image_bev (set below, once the lanes can lift)
        # per-quadrant LUTs, lifter LUT feeds and quadrant_cameras' answers, made once per LUT (lut_views.py)
        self._views = opened.views
        # per-camera lifts of image updates (camera_terms.py); None: every update runs the lifter graph
        self._terms: CameraTerms | None = opened.terms
        if self._terms is not None:  # its term and tail runs are recorded too, under their own names
            self._terms.recordings = _recordings_of(weakref.ref(self))
        if self.uses_images and self._lut is not None:
            self._blank_bev = self._lift_blank()
        log.info("streamdet: %s (%s, %d slices) on %s", self.export_dir, self.precision_label, self.num_slices, list(self.providers))
        if self.providers[0] != CPU_PROVIDER and "int8" in (config.image_precision, config.precision):  # a lane's graphs
            log.warning("streamdet: int8 graphs on %s: their quantize / dequantize pairs are made for x86 CPUs (uint8 "
                        "activations) and run slower there than the fp32 or fp16 graphs", self.providers[0])  # fmt: skip

    def _provider_options(self, entry: GraphEntry) -> dict[str, dict[str, str]] | None:
        """TensorRT's options for one graph where TensorRT is among the providers (export_open.provider_options)."""
        return provider_options(entry, export_dir=self.export_dir, config=self.config, image=self.image,
                                camera_names=self.camera_names, num_slices=self.num_slices, max_pillars=self._max_pillars)  # fmt: skip

    def _executed_gmac(self, graph: str, **sizes: int) -> float:
        """GMAC of one run of ``graph`` at these sizes (export_open.executed_gmac), for the stats."""
        return executed_gmac(self._graph_entries[graph], **sizes)

    @property
    def precision_label(self) -> str:
        """``"fp32"``, or ``"int8 image lane + fp32 slices"`` when the lanes differ."""
        c = self.config
        return lane_precision_label(c.precision, c.image_precision if self.uses_images else None)

    # ---- calibration ---------------------------------------------------------------------------
    @property
    def lut(self) -> Lut:
        """The projection LUT in use; a LiDAR-only export has none (NoImageLaneError)."""
        if self._lut is None:
            raise NoImageLaneError(self._no_image_lane("it has no projection LUT"))
        return self._lut

    def _no_image_lane(self, what: str) -> str:
        return no_image_lane(self.export_dir, what)

    def _check_lut(self, lut: Lut) -> Lut:
        """``lut`` if it fits this detector (export_open.check_lut: the check of the export's own LUT too)."""
        return check_lut(lut, self.image, self.camera_names, self.grid, self.export_dir, self.manifest)

    def set_calibration(self, calibration: Rig | Lut | Mapping | str | os.PathLike, relift: bool = True) -> None:
        """Swap the projection LUT without recreating sessions: a Rig, a Lut, a parsed calibration.json (a dict),
        or the path of a calibration.json or a lut.npz.

        The calibration must name the export's cameras in its order with the aspect ratio of its images
        (CalibrationError otherwise, and the LUT in use stays). A camera that sees no voxel is accepted with a
        BlindCameraWarning naming it, one that now sees another part of the grid than with the previous calibration
        (turned around, swapped) with a CameraMovedWarning. The newest cached image set is lifted again, so the next slice sees the new
        calibration at once (a quadrant the last update cleared, none of its cameras being given, stays cleared until
        the next update, even where the new LUT makes it read a camera that update gave). A LiDAR-only export has no calibration to set: NoImageLaneError. The rig the LUT in
        use was built from given again (an equal Rig, dict or calibration.json: the same ``Rig.sha256``, as a vehicle
        republishing its calibration sends) returns at once: no LUT build, no re-lift. (A LUT read from a file, the
        export's lut.npz included, may have been built otherwise: the first such call builds one from the rig.)

        ``relift`` False drops the cached image BEV instead of lifting it again (slices read no image until the next
        ``update_images``): for a caller whose next step feeds new images of the new rig, which would replace the
        re-lifted BEV unread (the offline pipeline, ``pipeline.use_sample_calibration``). On a closed detector, or one
        closed while the LUT was built: DetectorClosed (nothing installed). A re-lift that fails (an onnxruntime
        error) leaves the new LUT in use and the cached image BEV dropped, as ``relift`` False does, and raises.

        Calls from several threads: the one started last wins; one started earlier that finishes its LUT build later
        installs nothing (``StreamingRunner.submit_calibration`` runs them one at a time, in order).
        """
        if self._swap_calibration(calibration, relift):
            release_free_memory()  # the LUT build's temporaries: freed, but kept mapped by the allocator (heap.py)

    def _swap_calibration(self, calibration: Rig | Lut | Mapping | str | os.PathLike, relift: bool) -> bool:
        """set_calibration's work; False where it had none (the rig in use again)."""
        if not isinstance(relift, bool):
            raise ValueError(f"relift must be a bool, got {relift!r}")
        if not self.uses_images:
            # Refused rather than ignored: a caller that believes it recalibrated a camera model should learn it did not.
            raise NoImageLaneError(self._no_image_lane("set_calibration has nothing to calibrate"))
        if not self._sessions:  # closed: a LUT built now would only refill what close() let go of
            raise self._closed_error()
        with self._lock:
            self._calibration_seq += 1
            seq = self._calibration_seq
        if isinstance(calibration, (str, os.PathLike)):
            path = Path(calibration)
            is_lut = path.suffix.lower() == ".npz"  # lut.NPZ too (a case-insensitive file system's name): never read as JSON
            calibration = Lut.load(path, self.grid, len(self.camera_names)) if is_lut else Rig.from_calibration_json(path)
        elif isinstance(calibration, Mapping):
            calibration = Rig.from_calibration_json(calibration)
        if isinstance(calibration, Rig) and relift and self._is_current_rig(calibration, seq):
            return False  # the rig in use, published again: its LUT is the one in use (a vehicle republishes calibration)
        rig_sha = None
        if isinstance(calibration, Rig):
            rig_sha = calibration.sha256()
            calibration = self._build_lut(calibration)
        if not isinstance(calibration, Lut):
            raise CalibrationError(
                "set_calibration takes a Rig, a Lut, a parsed calibration.json or a path to a calibration.json / "
                f"lut.npz, got {type(calibration).__name__}"
            )
        lut = self._check_lut(calibration)
        # The new LUT's per-quadrant LUTs (and per-camera pieces) here, in the caller's thread: made on first use
        # instead, they would stall the image lane's next update and the phase-locked lane's scheduler meanwhile.
        qluts = self._luts_of(lut)
        if self._terms is not None:
            self._terms.warm(qluts)
        with self._calibration_lock:
            if seq < self._calibration_won:  # a call started later set its calibration already: this one is older
                return False
            self._calibration_won = seq
            moved = moved_cameras(self._lut, lut)  # against the LUT this swap replaces, not a concurrent swap's
            for name, iou in moved:
                msg = f"camera {name} now sees other voxels than with the previous calibration (overlap {iou:.2f})"
                log.warning("%s: %s", self.export_dir, msg)
                warnings.warn(msg, CameraMovedWarning, stacklevel=2)
            with self._lock:
                if not self._sessions:  # closed while the LUT was built: nothing installed on a closed detector
                    raise self._closed_error()
                self._lut = lut
                self._built_from = None if rig_sha is None else (lut, rig_sha)
                if not relift:
                    self._drop_images_locked(self._image_seq)  # an update already under way is of the old rig too
                    return True
                states = quadrant_states(self._image)
            try:
                self._relift(lut, qluts, states)
            except BaseException:
                # the LUT is in use: a BEV lifted with the old one must not stay under it (a retry with this rig is a
                # no-op): dropped, as relift=False does; the next update lifts with the new LUT
                with self._lock:
                    self._drop_images_locked(self._image_seq)
                raise
            return True

    def _relift(self, lut: Lut, qluts: tuple[QuadrantLut, ...], states: tuple[QuadrantState | None, ...]) -> None:
        """Re-lift the newest image set of every cached quadrant with ``lut`` (just installed; the caller holds the
        calibration lock). An update that finishes meanwhile under the old LUT lifts itself again (_install), so the
        loop ends once every cached quadrant was lifted with this LUT."""
        while True:
            stale = [(q, s) for q, s in enumerate(states) if s is not None and s.lut is not lut]
            if not stale:
                return
            groups: dict[int, list[tuple[int, QuadrantState]]] = {}  # quadrants lifted from one features array
            for q, s in stale:
                groups.setdefault(id(s.features), []).append((q, s))
            lifted = {}
            for members in groups.values():
                first = members[0][1]
                quadrants = tuple(q for q, _ in members)
                bevs = self._lift_quadrants(first.features, first.feature_cameras, quadrants, lut)
                # the new LUT may read other cameras in a quadrant: its timestamp follows them, and one the update
                # did not encode for it (a per-quadrant update) is lifted as zeros: missing, as a camera not given
                lifted.update({q: dataclasses.replace(s, bev=bev, lut=lut, timestamp=_restamp(s, qluts[q]),
                                                      cameras_missing=self._missing_after_swap(s, qluts[q]))
                               for (q, s), bev in zip(members, bevs)})  # fmt: skip
            with self._lock:
                current = list(quadrant_states(self._image))
                for q, s in stale:
                    if current[q] is s:  # not replaced by a newer update (or dropped: forget_images) meanwhile
                        current[q] = lifted[q]
                # every quadrant dropped meanwhile (the phase-locked lane's cameras timed out): no cache at all
                self._image = None if all(s is None for s in current) else ImageCache(tuple(current))
                states = quadrant_states(self._image)

    def _missing_after_swap(self, state: QuadrantState, qlut: QuadrantLut) -> tuple[str, ...]:
        """``state``'s missing cameras re-lifted with ``qlut``: those it missed, and those ``qlut`` reads that its
        feature maps do not hold, in the export's camera order."""
        missing = set(state.cameras_missing) | (set(qlut.camera_names) - set(state.feature_cameras))
        return tuple(n for n in self.camera_names if n in missing)

    def _is_current_rig(self, rig: Rig, seq: int) -> bool:
        """Whether the LUT in use is one this detector built from ``rig`` (the same sha256), once any swap under way
        has installed its LUT (the calibration lock): such a LUT is a function of the rig and the detector's fixed
        grid, image size and heights, so the swap would change nothing but cost a LUT build and a re-lift. A LUT read
        from a file or handed over (the export's lut.npz, a Lut) may have been built otherwise: never current. When
        current, call ``seq`` wins: a swap started before it and still building its LUT installs nothing."""
        sha = rig.sha256()

        def current() -> bool:
            built = self._built_from
            return built is not None and built[0] is self._lut and built[1] == sha

        if not current():  # the common answer for a new rig, without waiting on a swap under way
            return False
        with self._calibration_lock:
            if not current():
                return False
            self._calibration_won = max(self._calibration_won, seq)
            return True

    def _build_lut(self, rig: Rig) -> Lut:
        """The LUT of ``rig`` for this detector (export_open.export_lut: how the export's own is built too)."""
        return export_lut(rig, self.image, self.camera_names, self.grid, self.manifest)

    # ---- image lane ----------------------------------------------------------------------------
    def update_images(
        self, images: Mapping[str, np.ndarray], timestamp: float | None = None, quadrants: Sequence[int] | None = None,
        encoded: Mapping[str, np.ndarray] | None = None, camera_timestamps: Mapping[str, float] | None = None,
    ) -> ImageUpdate:  # fmt: skip
        """Encode and lift the given camera images (uint8 RGB (H, W, 3) by camera name) into the cached BEV.

        ``quadrants`` None (the full update): every camera given is encoded and all four quadrants are lifted. A
        strictly increasing list of quadrants (0..3) updates only those: only the cameras that see them (the LUT
        says which, ``quadrant_cameras``) are encoded, only their quadrants are lifted and get this timestamp;
        the other quadrants keep their older BEV. Both give the same BEV for the same images.

        ``encoded``: feature maps ``encode_images`` made of some of these same images, by camera name; those
        cameras are not encoded again (a scheduler lifting quadrants one by one encodes each image once).

        ``camera_timestamps``: the capture time of each given camera's image where the cameras fired at different
        moments (a LiDAR-synchronised rig); each lifted quadrant then gets the oldest of the times of the cameras
        that see it (given ones), rather than ``timestamp``, which still labels the update.

        Cameras not given are allowed: their features are zeros. A quadrant none of whose cameras is given is not
        lifted from zeros and stamped with this update's time: its older image BEV is dropped instead
        (``ImageUpdate.cleared``), so that its slices read what a quadrant without images reads (the LiDAR-only
        fallback where one is configured, else the camera-less BEV) and report no image age. Unknown names, wrong
        sizes or dtypes raise, and so does any call on a LiDAR-only export (NoImageLaneError).
        """
        if not isinstance(images, Mapping):
            raise ValueError(f"update_images takes a dict of camera name -> uint8 RGB (H, W, 3) image, got {type(images).__name__}")
        if not self.uses_images:
            raise NoImageLaneError(self._no_image_lane(f"update_images got cameras {sorted(map(str, images))} it cannot use"))
        timestamp = call_timestamp(timestamp)
        wanted = update_quadrants(quadrants)
        self.check_images(images)
        camera_ts = check_camera_timestamps(camera_timestamps, images)
        lut = self._lut  # the cameras to encode are chosen with it; a swap meanwhile re-plans (below)
        needed = self.camera_names if wanted == ALL_QUADRANTS else self._cameras_under(lut, wanted)
        used = tuple(n for n in needed if n in images)
        missing = tuple(n for n in needed if n not in images)
        if missing:
            log.info("update_images: cameras %s missing, their features are zeros", list(missing))
        with self._lock:
            self._image_seq += 1
            seq = self._image_seq
        known = self._check_encoded(encoded, images)
        t0 = time.perf_counter()
        features = self._encode(images, tuple(n for n in used if n not in known), needed)  # (J', C, Hf, Wf)
        for name in used:
            if name in known:
                features[needed.index(name)] = known[name]
        maps = {name: known[name] if name in known else features[needed.index(name)] for name in used}  # per-camera lifts
        cleared: set[int] = set()  # quadrants this update dropped, none of their cameras being given (_clear_blind)
        for attempt in range(MAX_RELIFTS_PER_UPDATE + 1):
            if attempt:
                # The calibration was swapped during this update: plan it again with the new LUT. Its quadrants may now
                # read a camera it was given but did not encode: that one is encoded too rather than lifted as zeros
                # (the cameras encoded already are kept).
                lut = self._lut
                needed = self.camera_names if wanted == ALL_QUADRANTS else self._cameras_under(lut, wanted)
                extra = tuple(n for n in needed if n in images and n not in maps)
                if extra:
                    enc = self._encode(images, extra, extra)  # (E, C, Hf, Wf)
                    maps = {**maps, **{name: enc[i] for i, name in enumerate(extra)}}
                used = tuple(n for n in needed if n in images)
                missing = tuple(n for n in needed if n not in images)
                features = np.zeros((max(1, len(needed)), *next(iter(maps.values())).shape), np.float32) if maps else \
                    self._encode(images, (), needed)  # fmt: skip
                for j, name in enumerate(needed):
                    if name in maps:
                        features[j] = maps[name]
            blind = tuple(q for q in wanted if not any(c in images for c in self._cameras_under(lut, (q,))))
            lifted = tuple(q for q in wanted if q not in blind)
            if blind and not self._clear_blind(lut, blind, seq):
                continue  # the calibration was swapped: plan again
            cleared.update(blind)
            installed = self._install(features, needed, lifted, seq, timestamp, missing, camera_ts, maps, lut) if lifted else True
            if installed is not None:
                break
        else:  # nothing installed; the quadrants an earlier plan cleared stay cleared
            installed = _gave_up(seq)
            blind, lifted = tuple(sorted(cleared)), tuple(q for q in wanted if q not in cleared)
        self.stats.record("image_total", (time.perf_counter() - t0) * 1e3)
        return ImageUpdate(timestamp, used, missing, superseded=not installed, quadrants=lifted, seq=seq, cleared=blind)

    def _clear_blind(self, lut: Lut, quadrants: tuple[int, ...], seq: int) -> bool:
        """Drop the image BEV of ``quadrants`` (none of whose cameras update ``seq`` was given) as of the calls before
        it: an older update still under way installs nothing there, a newer one already installed stays. False, and
        nothing dropped, when ``lut`` is no longer the LUT in use (the caller plans again: under the new LUT the
        quadrant may see a camera it was given, and this update must then still install there)."""
        with self._lock:
            if self._lut is not lut:
                return False
            self._drop_images_locked(seq - 1, quadrants, cameras_out=True, said_by=seq)
            return True

    def encode_images(self, images: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
        """The (C, Hf, Wf) float32 feature maps of the given camera images, by camera name (one encoder run), for
        ``update_images(..., encoded=...)``. Caches nothing."""
        if not isinstance(images, Mapping):
            raise ValueError(f"encode_images takes a dict of camera name -> uint8 RGB (H, W, 3) image, got {type(images).__name__}")
        if not self.uses_images:
            raise NoImageLaneError(self._no_image_lane(f"encode_images got cameras {sorted(map(str, images))} it cannot use"))
        self.check_images(images)
        used = tuple(n for n in self.camera_names if n in images)
        features = self._encode(images, used, used)  # (J_used, C, Hf, Wf)
        features.setflags(write=False)  # its views below cannot be made writable: safe to keep terms by identity
        maps = {name: features[j] for j, name in enumerate(used)}
        for f in maps.values():
            self._own_maps[id(f)] = f  # weak: gone with the caller's last reference
        return maps

    def warm_up(self, rounds: int = 2) -> None:
        """Run every graph ``rounds`` times on dummy inputs before the first real data (onnxruntime's first runs of
        a graph are slow: runtime_ort/warm_up.py), then drop the dummy image BEV and the latency statistics. Call it
        once after construction, before the first ``update_images`` / slice."""
        warm_up(self, rounds)

    def forget_images(self, through: int | None = None, quadrants: Sequence[int] | None = None, cameras_out: bool = False) -> None:
        """Drop the cached image BEV: slices read no image until the next ``update_images``. An update already under
        way when this is called installs nothing (its ``ImageUpdate.superseded`` is True).

        ``through``: only the image sets of the calls up to that ``ImageUpdate.seq`` (``warm_up`` drops its own
        dummy images so, never a real set that came after them).

        ``quadrants``: only those (a strictly increasing list of 0..3; None: all four); the others keep their BEV,
        and an update under way still installs there. The phase-locked image lane drops so a quadrant all of whose
        cameras are out (``LaneConfig.camera_timeout_s``): its slices then read no image (the camera-less BEV, or
        the LiDAR-only fallback), as before the first image, and passes ``cameras_out`` True: the slices of those
        quadrants then name their cameras in ``SliceResult.cameras_missing`` (False: no camera is said to be out).
        What a quadrant's slices say is set by the newest call that dropped it: this one, unless an update newer than
        ``through`` was given none of the quadrant's cameras and so cleared it."""
        if not isinstance(cameras_out, bool):
            raise ValueError(f"forget_images cameras_out must be True or False, got {cameras_out!r}")
        if through is not None and (isinstance(through, bool) or not isinstance(through, (int, np.integer)) or through < 0):
            raise ValueError(f"forget_images through must be None or an ImageUpdate.seq (an int >= 0), got {through!r}")
        wanted = update_quadrants(quadrants)
        with self._lock:
            self._drop_images_locked(self._image_seq if through is None else int(through), wanted, cameras_out)

    def _drop_images_locked(self, through: int, quadrants: tuple[int, ...] = ALL_QUADRANTS, cameras_out: bool = False,
                            said_by: int | None = None) -> None:  # fmt: skip
        """Drop the image sets of the update_images calls up to ``through`` (seq) in ``quadrants``, cached or still
        under way (``_install`` refuses them there); ``cameras_out``: because none of their cameras has a frame
        (``_cameras_out``), as update ``said_by`` found (None: a forget through ``through``). The caller holds
        ``_lock``."""
        floor = self._image_floor
        out = list(self._cameras_out)
        for q in quadrants:
            # Why q is empty is said by the newest call that dropped it: a forget through seq T, or an update S that
            # was given none of q's cameras (said_by). Neither an older forget (warm_up forgetting its own dummies)
            # nor the late clear of an update begun before a forget through it changes what a newer call said.
            newer = through >= self._out_said[q] if said_by is None else said_by > self._out_said[q]
            if newer:
                out[q] = cameras_out
                self._out_said[q] = through if said_by is None else said_by
            floor[q] = max(floor[q], through)
        self._cameras_out = tuple(out)
        kept = tuple(s if s is not None and s.seq > floor[q] else None for q, s in enumerate(quadrant_states(self._image)))
        self._image = None if all(s is None for s in kept) else ImageCache(kept)

    @property
    def camera_terms(self) -> bool:
        """Whether image updates (full and per-quadrant) use per-camera lifts (``DetectorConfig.camera_terms``,
        camera_terms.py)."""
        return self._terms is not None

    def prepare_terms(self, encoded: Mapping[str, np.ndarray]) -> int:
        """Make the per-camera lift terms of these feature maps (``encode_images``'s, by camera name) in every quadrant
        their cameras feed, so that a later ``update_images(..., quadrants=..., encoded=...)`` given the same arrays
        only sums the terms and runs the rest of the lifter. The number of terms made (0 without per-camera lifts)."""
        if self._terms is None:
            return 0
        self._check_feature_maps(encoded)
        with self._lock:
            lut = self._lut
        # only encode_images' maps: a caller's array is copied by update_images, so terms made of it would not be used
        own = {name: f for name, f in encoded.items() if self._own_maps.get(id(f)) is f}
        return self._terms.prepare(self._luts_of(lut), own) if own else 0

    def _check_feature_maps(self, encoded: Mapping[str, np.ndarray]) -> None:
        img = self.image
        shape = (int(self.manifest.preset["channels"]), img.feature_height, img.feature_width)
        if not isinstance(encoded, Mapping):
            raise ValueError(f"encoded must be None or a dict of camera name -> {shape} float32 feature map, got {type(encoded).__name__}")
        for name, f in encoded.items():
            if name not in self.camera_names:
                raise ValueError(f"encoded names unknown camera {name!r}; this export knows {list(self.camera_names)}")
            if not isinstance(f, np.ndarray) or f.dtype != np.float32 or f.shape != shape:
                got = f"{getattr(f, 'dtype', type(f).__name__)} {getattr(f, 'shape', '')}"
                raise ValueError(f"encoded[{name!r}] must be a float32 feature map of shape {shape} (encode_images), got {got}")
            if self._own_maps.get(id(f)) is not f and not np.isfinite(f).all():  # encode_images' own are checked
                raise ValueError(f"encoded[{name!r}] holds NaN or infinite values: it would blind every slice reading it")

    def _check_encoded(self, encoded: Mapping[str, np.ndarray] | None, images: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
        if encoded is None:
            return {}
        for name in encoded if isinstance(encoded, Mapping) else ():
            if name not in images:
                raise ValueError(f"encoded names camera {name!r}, whose image this update was not given")
        self._check_feature_maps(encoded)
        # Per-camera terms are kept by the map object they were made from (camera_terms.py): only encode_images'
        # maps, read-only views of a read-only array, cannot change under that identity. A caller's own array may be
        # refilled in place for the next frame, so it is copied: its terms are never mistaken for the new frame's.
        return {name: f if self._own_maps.get(id(f)) is f else _frozen_copy(f) for name, f in encoded.items()}

    def quadrant_cameras(self, quadrants: Sequence[int]) -> tuple[str, ...]:
        """The cameras whose feature maps the LUT in use reads in these quadrants, in the export's camera order."""
        # the phase-locked lane asks several hundred times a second, holding the GIL: a kept answer before any check
        if isinstance(quadrants, (list, tuple)) and all(type(q) is int for q in quadrants):
            cams = self._views.known_cameras(self._lut, tuple(quadrants))
            if cams is not None:
                return cams
        return self._cameras_under(self.lut, update_quadrants(quadrants))

    def _cameras_under(self, lut: Lut, quadrants: tuple[int, ...]) -> tuple[str, ...]:
        """``quadrant_cameras`` of valid ``quadrants`` under ``lut`` (the LUT in use, or one a swap just replaced)."""
        return self._views.cameras(lut, quadrants, in_use=self._lut)  # a kept answer first (lut_views.py)

    def check_images(self, images: Mapping[str, np.ndarray]) -> None:
        """ValueError unless ``images`` is a non-empty dict of known camera names to uint8 RGB (H, W, 3) images of
        this detector's size (what update_images and encode_images refuse)."""
        img = self.image
        unknown = [n for n in images if n not in self.camera_names]
        if unknown:
            raise ValueError(f"unknown camera names {unknown}; this export knows {list(self.camera_names)}")
        if not images:
            raise ValueError(f"no camera image given: at least one of {list(self.camera_names)} is needed")  # update_images and encode_images
        for name in self.camera_names:
            if name not in images:
                continue
            a = images[name]
            if not isinstance(a, np.ndarray) or a.dtype != np.uint8 or a.shape != (img.height, img.width, 3):
                got = f"{getattr(a, 'dtype', type(a).__name__)} {getattr(a, 'shape', '')}"
                raise ValueError(
                    f"image {name!r} must be uint8 RGB of shape ({img.height}, {img.width}, 3) for this detector, got {got}"
                )

    def _encode(self, images: Mapping[str, np.ndarray], used: tuple[str, ...], cameras: tuple[str, ...]) -> np.ndarray:
        """(J', C, Hf, Wf) float32 feature maps of ``cameras``: the encoder's for those ``used``, zeros for the rest."""
        img = self.image
        c = int(self.manifest.preset["channels"])
        if not used:
            return np.zeros((max(1, len(cameras)), c, img.feature_height, img.feature_width), dtype=np.float32)
        batch = np.stack([images[n] for n in used])  # (J_used, H, W, 3)
        with self.stats.time("image_encoder", self._executed_gmac("image_encoder", J=len(used), H=img.height, W=img.width)):
            (enc,) = self._run_graph("image_encoder", {"images": batch})  # (J_used, C, Hf, Wf)
        if enc.shape[2:] != (img.feature_height, img.feature_width):
            # the LUT's rows address (Hf, Wf) maps: another size would gather the wrong cells without an error
            raise ValueError(
                f"image_encoder made {enc.shape[3]}x{enc.shape[2]} feature maps from {img.width}x{img.height} images, "
                f"the LUT expects {img.feature_width}x{img.feature_height}"
            )
        if len(used) == len(cameras):
            return np.ascontiguousarray(enc, dtype=np.float32)
        features = np.zeros((len(cameras), *enc.shape[1:]), dtype=np.float32)  # (J', C, Hf, Wf)
        features[[cameras.index(n) for n in used]] = enc
        return features

    def _install(
        self, features: np.ndarray, cameras: tuple[str, ...], quadrants: tuple[int, ...], seq: int, timestamp: float,
        missing: tuple[str, ...], camera_timestamps: Mapping[str, float] | None, maps: Mapping[str, np.ndarray] | None,
        lut: Lut,
    ) -> bool | None:  # fmt: skip
        """Lift ``features`` into ``quadrants`` with ``lut`` and cache each quadrant unless a newer image set is
        cached there already or the set was dropped meanwhile (forget_images, set_calibration(relift=False)); False
        if that was so in every one. With ``camera_timestamps`` a quadrant's timestamp is the oldest of its cameras'
        (the LUT's cameras of that quadrant among those given), else ``timestamp``.

        None, and nothing cached, when ``lut`` is no longer the LUT in use, before or after the lift (a calibration
        swap): the caller plans the update again with the new LUT, so the cache never holds a BEV of an old
        calibration once set_calibration has returned."""
        stamps = tuple(sorted(camera_timestamps.items())) if camera_timestamps else ()
        with self._lock:
            if self._lut is not lut:
                return None
            current, floor = quadrant_states(self._image), tuple(self._image_floor)
        todo = tuple(q for q in quadrants if seq > floor[q] and (current[q] is None or current[q].seq < seq))
        if not todo:
            return False
        bevs = self._lift_quadrants(features, cameras, todo, lut, maps)
        for q, bev in zip(todo, bevs):  # tens of microseconds a quadrant: a sliver of its lift
            if not np.isfinite(bev).all():
                raise GraphRunError(f"the image lane made a non-finite image BEV for quadrant {q} ({self.precision_label}: "
                                    "an encoder or lifter graph overflowing?); the cached BEV is kept")  # fmt: skip
        qluts = self._luts_of(lut) if camera_timestamps else ()
        with self._lock:
            if self._lut is not lut:
                return None
            states = list(quadrant_states(self._image))
            installed = False
            for q, bev in zip(todo, bevs):
                if seq <= self._image_floor[q]:  # dropped there while it lifted
                    continue
                if states[q] is None or states[q].seq < seq:
                    stamp = quadrant_timestamp(qluts[q].camera_names, camera_timestamps, cameras, timestamp) if qluts else timestamp
                    states[q] = QuadrantState(bev, features, cameras, stamp, missing, seq, lut, stamps, timestamp)
                    installed = True
            if installed:
                self._image = ImageCache(tuple(states))
            return installed

    def _lift(self, features: np.ndarray, lut: Lut) -> np.ndarray:
        """The full lift: (4, C, Yq, Xq) from the (J, C, Hf, Wf) feature maps of every camera and the whole LUT."""
        with self.stats.time("volumetric_lifter", self._executed_gmac("volumetric_lifter", Q=NUM_QUADRANTS)):
            (bev,) = self._run_graph("volumetric_lifter", {"features": features, **self._lut_feeds(lut, features)})
        return bev  # (4, C, Yq, Xq)

    def _lift_quadrants(
        self, features: np.ndarray, cameras: tuple[str, ...], quadrants: tuple[int, ...], lut: Lut,
        maps: Mapping[str, np.ndarray] | None = None,
    ) -> list[np.ndarray]:  # fmt: skip
        """(1, C, Yq, Xq) image BEV of each of ``quadrants`` from the (J', C, Hf, Wf) feature maps of ``cameras``.

        With per-camera lifts (camera_terms.py), each quadrant from its cameras' terms, kept per feature map: ``maps``
        (camera -> (C, Hf, Wf), the cameras given, by the objects the caller encoded) names them, else the rows of
        ``features``; a full update makes every camera's terms first, one run per camera for all its quadrants.
        Without them: all four quadrants from every camera in one lifter run with the whole LUT, otherwise one run per
        quadrant with its own rows of the LUT (quadrant_lut.py), fed the feature maps of the cameras that see it
        (zeros for one this features array does not hold, e.g. after a calibration swap widened the quadrant's
        view)."""
        if quadrants == ALL_QUADRANTS and cameras == self.camera_names and self._terms is None:
            bev = self._lift(features, lut)  # (4, C, Yq, Xq)
            return [bev[q : q + 1] for q in range(NUM_QUADRANTS)]  # (1, C, Yq, Xq) views, no copy
        qluts = self._luts_of(lut)
        if self._terms is not None:
            if maps is None:
                maps = {name: features[j] for j, name in enumerate(cameras)}
            if quadrants == ALL_QUADRANTS:  # every camera's terms in one run each, then one tail per quadrant
                self._terms.prepare(qluts, maps)
            return [self._terms.lift(q, qluts[q], maps) for q in quadrants]
        out = []
        for q in quadrants:
            qlut = qluts[q]
            maps = select_maps(features, cameras, qlut.camera_names)
            feeds = {"features": maps, **self._lut_feeds(qlut, maps)}
            with self.stats.time("volumetric_lifter", self._executed_gmac("volumetric_lifter", Q=1)):
                (bev,) = self._run_graph("volumetric_lifter", feeds)  # (1, C, Yq, Xq)
            out.append(bev)
        return out

    def _lut_feeds(self, lut: Lut | QuadrantLut, maps: np.ndarray) -> dict[str, np.ndarray]:
        """The lifter's LUT feeds of ``lut`` for the (J, C, Hf, Wf) ``maps`` in the export's LUT layout."""
        return self._views.lifter_feeds(lut, maps)

    def _luts_of(self, lut: Lut) -> tuple[QuadrantLut, ...]:
        """The per-quadrant LUTs of ``lut``, made once per LUT (those of the LUT in use and of ``lut`` kept)."""
        return self._views.quadrant_luts(lut, in_use=self._lut)

    @property
    def image_timestamp(self) -> float | None:
        """Timestamp of the oldest quadrant of the cached image BEV; None before any image update."""
        cache = self._image
        return None if cache is None else cache.timestamp

    @property
    def image_timestamps(self) -> tuple[float | None, ...]:
        """Timestamp of each quadrant's cached image BEV (None: no image yet), quadrants 0..3."""
        return tuple(None if s is None else s.timestamp for s in quadrant_states(self._image))

    @property
    def image_state(self) -> ImageCache | None:
        """The cached image BEV the next slice reads (read-only); None before any image update.

        Never changed in place: every update or re-lift swaps in a new one, so ``det.image_state is before`` tells
        whether a call changed the cache. It has ``bev`` (a copy of every quadrant), ``features``, ``seq`` (the
        `update_images` call, in call order, of the newest set cached), ``timestamp``, ``lut`` (the LUT it was
        lifted with; None while quadrants differ) and ``quadrants`` (each quadrant's state, None without images:
        its slices read ``blank_image_bev``, where ``bev`` shows zeros). Its arrays are the detector's own: read
        them, never write them."""
        return self._image

    @property
    def slice_runs_at_top_k(self) -> int:
        """Slice-graph runs so far in which a quadrant's K-th box (the last the graph decodes: the export's
        ``post.top_k_per_quadrant``, ``streamdet-export --top-k``) passed the score threshold, so the cap may have cut boxes."""
        return self._runs_at_top_k

    @property
    def postprocess(self) -> PostprocessConfig:
        """The post-processing every slice runs: score threshold (the config's, else the export's), sector
        restriction and NMS settings."""
        return self._post

    # ---- slice lane ----------------------------------------------------------------------------
    def detect_slice(
        self, points: np.ndarray, slice_index: int, timestamp: float | None = None, num_slices: int | None = None
    ) -> SliceResult:
        """Detections of slice `slice_index` of `num_slices` (None: the detector's) from its (N, 6) float32 points
        (x, y, z, r, t, s).

        Uses the newest cached image BEV of the slice's quadrant(s) (``blank_image_bev`` where there is none); a
        LiDAR-only export's slice graph takes the quadrant ids instead. NaN / inf points are dropped and counted
        (``num_nonfinite_dropped``), so are points outside the grid or the slice's quadrant(s)
        (``num_outside_dropped``); an empty slice gives no detections. Only float32 is accepted: this is the hot
        path, and a silent conversion would copy every slice (``detect_sweep`` converts, once per sweep).
        ``points`` is only read, during the call.
        """
        n = self._slices(num_slices)
        problem = slice_index_problem(slice_index, n)
        if problem is not None:
            raise ValueError(problem)
        return self._detect_run((points,), (int(slice_index),), (timestamp,), n)[0]

    def detect_slices(
        self,
        points: Sequence[np.ndarray],
        slice_indices: Sequence[int],
        timestamps: Sequence[float | None],
        num_slices: int | None = None,
    ) -> tuple[SliceResult, ...]:
        """Consecutive slices of one rotation and one quadrant detected in **one** slice-graph run (what the slice
        lane does when it has fallen behind, `LaneConfig.coalesce_slices`): one `SliceResult` per slice, in order.

        Each slice's points are checked as in `detect_slice`; they are pillarised together and each box goes to the
        slice whose sector holds its centre (runtime_ort/coalesce.py). Every result has its own timestamp, point
        count and image age; the run's pillar count and dropped-point counts are reported once, on the last
        slice (0 on the others), so that sums over results stay true; ``coalesced`` names the slices of the run.
        """
        n = self._slices(num_slices)
        ks = check_coalesced(slice_indices, n, self.config.start_deg, self.config.clockwise)
        points, timestamps = tuple(points), tuple(timestamps)
        if len(points) != len(ks) or len(timestamps) != len(ks):
            raise ValueError(f"detect_slices takes one points array and one timestamp per slice: {len(ks)} slices, "
                             f"{len(points)} point arrays, {len(timestamps)} timestamps")  # fmt: skip
        return self._detect_run(points, ks, timestamps, n)

    def _detect_run(
        self, points: tuple[np.ndarray, ...], ks: tuple[int, ...], timestamps: tuple[float | None, ...], n: int
    ) -> tuple[SliceResult, ...]:
        """One slice-graph run over slices ``ks`` of ``n`` (valid: the callers checked them)."""
        timestamps = tuple(call_timestamp(t) for t in timestamps)
        for p in points:
            problem = slice_points_problem(p)
            if problem is not None:
                raise ValueError(problem)
        total = sum(p.shape[0] for p in points)
        if total > MAX_SLICE_POINTS:  # before any work: a corrupt count (or zero strides) would need gigabytes
            raise ValueError(f"a slice run holds {total} points, over the {MAX_SLICE_POINTS} of MAX_SLICE_POINTS (core/points.py)")
        if not self._sessions:  # closed: a slice without pillars runs no graph, and would answer "no objects"
            raise self._closed_error()
        quadrants = quadrants_of_sector(ks[0], n, self.config.start_deg, self.config.clockwise)
        t0 = time.perf_counter()
        cache = quadrant_states(self._image)  # one read: a consistent view of the cache
        out = self._cameras_out  # (read after the cache: a drop between the two reads only renames a quadrant's absence)
        states = tuple(cache[q] for q in quadrants)
        stamps = [s.timestamp for s in states if s is not None]
        image_ts = min(stamps) if stamps else None
        # the newest slice's image age decides: the fallback is for images too old at the moment of the run
        image_age = None if image_ts is None else max(timestamps) - image_ts
        if image_age is not None and not self._warned_clocks and not -CLOCKS_APART_S <= image_age <= IMPLAUSIBLE_IMAGE_AGE_S:
            self._warn_clocks(max(timestamps), image_ts)
        if not self._warned_slice_index:
            self._check_slice_index_column(points, ks, n)
        fallback = self._fallback is not None and needs_fallback(None not in states, image_age, self.config.fallback_after_s)
        crop = self._fallback.slice_crop if fallback else self.slice_crop
        run_points = points[0] if len(points) == 1 else np.concatenate(points)  # (N, 6): each point keeps its own s
        with self.stats.time("pre"):
            pillars = pillarize(run_points, self.grid, quadrants, self._max_points_per_pillar, self._max_pillars, crop=crop)
        if pillars.num_out_of_range_dropped and not self._warned_out_of_range:
            self._warned_out_of_range = True  # once: a sensor set up wrongly would say it with every slice
            log.warning("%s: %d point(s) of slice %d dropped for a reflectance outside %s, a time outside [0, %g] s or a "
                        "slice index outside [0, %d] (core/points.py); a sensor with another intensity range needs its "
                        "intensity scaled to 0..255 (CloudFields.intensity_scale); counted in num_outside_dropped",
                        self.export_dir, pillars.num_out_of_range_dropped, ks[-1], list(REFLECTANCE_RANGE),
                        MAX_POINT_TIME_S, MAX_SLICE_INDEX)  # fmt: skip
        nonfinite = 0
        if pillars.num_pillars == 0:
            dets = Detections.empty()
        else:
            num_maps = len(quadrants) if crop else 1
            if fallback:  # the LiDAR-only graph: the quadrant ids tell it Q (none without the crop)
                feeds, graph = pillars.as_feeds(quadrants if crop else None), FALLBACK_GRAPH
            elif self.uses_images:
                # the image BEV, or its precomputed image half (the manifest's image_layout names the input)
                feeds, graph = {**pillars.as_feeds(), self.manifest.image_layout: self._image_bev(states)}, "slice_head"
            else:  # the quadrant ids tell a LiDAR-only graph Q; without the crop Q is 1 and it takes none
                feeds, graph = pillars.as_feeds(quadrants if crop else None), "slice_head"
            with self.stats.time(graph, self._executed_gmac(graph, Q=num_maps)):
                boxes, scores, labels = self._run_graph(graph, feeds)
            nonfinite = self._check_slice_outputs(graph, boxes, scores, labels, ks[-1])
            if top_k_reached(scores, self._post.score_threshold):
                with self._cap_lock:
                    self._runs_at_top_k += 1
            with self.stats.time("post"):
                run = SliceRun(ks, n, self.config.start_deg, self.config.clockwise)  # restrict_to_sector: by slice index
                dets = postprocess_slice(boxes, scores, labels, quadrants, self.grid, self._post, crop=crop, slices=run)
        self.stats.record("slice_total", (time.perf_counter() - t0) * 1e3)
        parts = split_by_slice(dets, ks, n, self.config.start_deg, self.config.clockwise)
        last = len(ks) - 1
        missing = self._cameras_missing(quadrants, states, out)
        return tuple(
            SliceResult(
                detections=part,
                slice_index=k,
                num_slices=n,
                timestamp=ts,
                image_timestamp=image_ts,
                image_age_s=None if image_ts is None else ts - image_ts,
                num_points=int(p.shape[0]),
                num_pillars=pillars.num_pillars if i == last else 0,
                num_nonfinite_dropped=pillars.num_nonfinite_dropped if i == last else 0,
                num_outside_dropped=pillars.num_outside_dropped if i == last else 0,
                num_points_dropped=pillars.num_points_dropped if i == last else 0,
                num_nonfinite_outputs=nonfinite if i == last else 0,
                fallback=fallback,
                coalesced=ks if len(ks) > 1 else (),
                cameras_missing=missing,
            )
            for i, (k, p, ts, part) in enumerate(zip(ks, points, timestamps, parts))
        )

    def _warn_clocks(self, slice_ts: float, image_ts: float) -> None:
        """Once per detector: a slice's image age that no image lane explains (the image stamped over CLOCKS_APART_S
        after the slice, or over IMPLAUSIBLE_IMAGE_AGE_S before it) is two clocks read as one, and every
        ``image_age_s`` (and a fallback's age rule) is meaningless until the caller fixes its stamps."""
        self._warned_clocks = True
        log.warning("%s: slice timestamp %.17g and image timestamp %.17g are %.6g s apart: are both lanes on the same "
                    "clock (timestamp=None is time.monotonic(), a driver's header stamp is not) and in seconds (ROS "
                    "stamps are nanoseconds)? SliceResult.image_age_s means nothing until they are (logged once)",
                    self.export_dir, slice_ts, image_ts, slice_ts - image_ts)  # fmt: skip

    def _check_slice_index_column(self, points: tuple[np.ndarray, ...], ks: tuple[int, ...], n: int) -> None:
        """Once per detector: a slice whose slice-index column is not the feature of its slice in this scan layout
        (``core.slicing.feature_index``, what split_sweep and the ROS adapter write; not k itself in a layout that
        starts elsewhere or turns clockwise): the model then reads another sector's index, and nothing else says so.
        Only its first and last points: a caller's numbering applies to all of a slice's points alike, and a pass over
        every point would cost every slice."""
        for p, k in zip(points, ks):
            if p.shape[0] == 0:
                continue
            want = self._feature_indices.get((k, n))
            if want is None:
                want = self._feature_indices[(k, n)] = feature_index(k, n, self.config.start_deg, self.config.clockwise)
            for got in (float(p[0, SLICE_INDEX]), float(p[-1, SLICE_INDEX])):
                if got != want and math.isfinite(got):  # a NaN is dropped and counted as one
                    self._warned_slice_index = True
                    log.warning("%s: slice %d of %d has %g in its slice-index column (points[:, %d]), the feature of "
                                "that slice's points being %d in this scan layout (start_deg %g, clockwise %s: "
                                "core.slicing.feature_index, which split_sweep writes); numbered in scan order, the "
                                "model reads another sector's index (logged once)", self.export_dir, k, n, got,
                                SLICE_INDEX, want, self.config.start_deg, self.config.clockwise)  # fmt: skip
                    return

    def _check_slice_outputs(self, graph: str, boxes: np.ndarray, scores: np.ndarray, labels: np.ndarray, k: int) -> int:
        """The number of output rows with a NaN or inf (dropped by the post-processing, counted in SliceResult and
        logged once: a graph overflowing, e.g. fp16 on unusual input). Labels outside the classes or scores outside
        [0, 1] are no output of a slice graph at all: GraphRunError naming it (the run's input was fine)."""
        bad = ~(np.isfinite(boxes).all(axis=-1) & np.isfinite(scores))  # (Q, K)
        nonfinite = int(bad.sum())
        if nonfinite and not self._warned_nonfinite_outputs:
            self._warned_nonfinite_outputs = True
            log.warning("%s: %s gave %d output row(s) with NaN or inf in slice %d, dropped and counted in "
                        "SliceResult.num_nonfinite_outputs (logged once)", self.export_dir, graph, nonfinite, k)  # fmt: skip
        file = self._graph_files[graph]  # not the session: close() may have released it meanwhile
        wrong = (labels < 0) | (labels >= len(self.manifest.class_names))
        if wrong.any():
            raise GraphRunError(f"{file}: det_labels holds {int(labels[wrong][0])}, outside the {len(self.manifest.class_names)} classes")
        ok = scores[~bad]
        if ok.size and not (ok.min() >= 0.0 and ok.max() <= 1.0):
            raise GraphRunError(f"{file}: det_scores holds {float(ok.min()):.6g}..{float(ok.max()):.6g}, outside [0, 1]")
        return nonfinite

    def _cameras_missing(self, quadrants: tuple[int, ...], states: tuple[QuadrantState | None, ...],
                         cameras_out: tuple[bool, ...]) -> tuple[str, ...]:  # fmt: skip
        """The cameras whose features were zeros (not given to the image update that made the BEV) among those the LUT
        of each quadrant read reads there, and every camera the current LUT reads in a quadrant dropped because none
        of its cameras had a frame (``cameras_out``, per quadrant 0..3), in the export's camera order."""
        missing: set[str] = set()
        lut = self._lut
        for q, state in zip(quadrants, states):
            if state is None:
                if cameras_out[q] and lut is not None:
                    missing.update(self._cameras_under(lut, (q,)))
            elif state.cameras_missing and state.lut is not None:  # () on every slice but a camera out
                missing.update(set(state.cameras_missing) & set(self._cameras_under(state.lut, (q,))))
        return tuple(c for c in self.camera_names if c in missing) if missing else ()

    def _image_bev(self, states: tuple[QuadrantState | None, ...]) -> np.ndarray:
        """(Q, C, Yq, Xq) image BEV of the slice's quadrants, or in the image_half layout their image half
        (Q, C0, Yh, Xh); for a quadrant without images (none yet, dropped, or all its cameras out) the camera-less
        BEV (``blank_image_bev``)."""
        if len(states) == 1 and states[0] is not None:
            return states[0].bev  # (1, C, Yq, Xq), no copy
        blank = self.blank_image_bev
        if len(states) == 1:
            return blank
        return np.concatenate([blank if s is None else s.bev for s in states])  # (Q, C, Yq, Xq)

    @property
    def blank_image_bev(self) -> np.ndarray:
        """(1, C, Yq, Xq) (image_half layout: (1, C0, Yh, Xh)) what a quadrant's slices read where there is no image
        BEV (none yet, dropped, or none of its cameras sending): the image lane's lift of zero feature maps, made
        with its own graphs when the detector is built (``_lift_blank``). A LiDAR-only export has none (NoImageLaneError)."""
        blank = self._blank_bev
        if blank is None:
            if not self.uses_images:
                raise NoImageLaneError(self._no_image_lane("it has no camera-less image BEV"))
            raise self._closed_error()
        return blank

    def _lift_blank(self) -> np.ndarray:
        """The lift of zero feature maps (no camera), for ``blank_image_bev``. Not zeros: the lifter's biases make it
        a constant map away from the quadrant's edges, and the shipped models (trained with images from the first
        step: neither map is in their training) read it far better than an all-zero map (docs/replay.md, "A quadrant
        without cameras"). The same for every quadrant and calibration (zero feature maps gather zeros through any
        LUT), so one lift serves for good; its run is not counted in ``stats``."""
        zeros = self._encode({}, (), ())  # (1, C, Hf, Wf)
        (bev,) = self._lift_quadrants(zeros, (), (0,), self._lut, {})  # (1, C, Yq, Xq)
        if not np.isfinite(bev).all():
            raise GraphRunError(f"{self.export_dir}: the image lane's lift of zero features is not finite ({self.precision_label})")
        self.stats.reset()
        bev = np.array(bev, dtype=np.float32)  # its own copy, read-only: every slice without images shares it
        bev.setflags(write=False)
        return bev

    def detect_sweep(self, sweep: np.ndarray, timestamp: float | None = None, num_slices: int | None = None) -> Detections:
        """Slice a full (N, 5) sweep (x, y, z, intensity 0..255, ring) into `num_slices` (None: the detector's),
        detect every slice, merge with per-class NMS.

        This is how the paper evaluates a streaming model on a sweep; one detector (one cached image BEV) can
        score several slice counts. Any real numeric dtype (float, int, uint) is converted to float32, as a file
        reader hands it over; bool, complex, object or string arrays raise ValueError.
        """
        return self.detect_sweep_slices(sweep, timestamp, num_slices).detections

    def detect_sweep_slices(self, sweep: np.ndarray, timestamp: float | None = None, num_slices: int | None = None) -> SweepResult:
        """``detect_sweep`` keeping what each slice saw and found (its points and ``SliceResult``). A sweep point
        whose x or y is NaN has no azimuth and so is in no slice's points: it is counted in the first slice's
        ``num_nonfinite_dropped`` (beside that slice's own ``num_points``)."""
        n = self._slices(num_slices)
        if isinstance(sweep, np.ma.MaskedArray):
            raise ValueError("sweep must be a plain array, got a masked array (its mask would be ignored)")
        sweep = check_sweep(sweep)
        if sweep.dtype.kind not in "fiu":
            raise ValueError(f"sweep must hold real numbers (float or int), got dtype {sweep.dtype}")
        if sweep.shape[0] > MAX_SWEEP_POINTS:
            raise ValueError(f"sweep holds {sweep.shape[0]} points, over the {MAX_SWEEP_POINTS} of MAX_SWEEP_POINTS (core/points.py)")
        slices = split_sweep(sweep.astype(np.float32, copy=False), n, self.config.start_deg, clockwise=self.config.clockwise)
        results = [self.detect_slice(pts, k, timestamp, n) for k, pts in enumerate(slices)]
        with self.stats.time("sweep_nms"):
            merged = aggregate_sweep([r.detections for r in results], self.config.nms)
        # a point whose x or y is NaN has no azimuth, so split_sweep put it in no slice: counted with the first
        # slice's non-finite points, so that every point the sweep lost is in some SliceResult's count
        no_azimuth = sweep.shape[0] - sum(s.shape[0] for s in slices)
        if no_azimuth:
            results[0] = dataclasses.replace(results[0], num_nonfinite_dropped=results[0].num_nonfinite_dropped + no_azimuth)
        return SweepResult(merged, tuple(results), tuple(slices))

    def _slices(self, num_slices: int | None) -> int:
        return slice_count(num_slices, self.num_slices, self.config.start_deg)

    # ---- graph runs ----------------------------------------------------------------------------
    @property
    def sessions(self) -> dict[str, GraphSession]:
        """The sessions in use by graph name (the image graphs' only with an image lane)."""
        return dict(self._sessions)

    def _run_graph(self, name: str, feeds: Feeds) -> list[np.ndarray]:
        session = self._sessions.get(name)
        if session is None:
            raise self._closed_error()
        recordings = self._recordings  # the blocks open when the run starts record it (one that opens meanwhile not)
        outputs = session.run(feeds)
        for recording in recordings:
            recording.add(name, feeds, outputs)
        return outputs

    @contextmanager
    def recording(self, recording: GraphRecording | None = None) -> Iterator[GraphRecording]:
        """Record every graph run of this detector (any lane, any thread) while the block runs: its graph, the exact
        feeds it was given and its outputs (runtime_ort/recording.py), appended to ``recording`` (None: a new
        one). Blocks may nest or overlap; each records what ran while it was open. With per-camera lifts
        (``camera_terms``) an image update runs no ``volumetric_lifter``: its term and tail runs are recorded as
        ``lifter_term`` and ``lifter_tail`` (camera_terms.py).

            with detector.recording() as rec:
                detect_sample(detector, sample)
            rec.feeds("slice_head")  # the pillar tensors and image BEV of every non-empty slice
        """
        recording = GraphRecording() if recording is None else recording
        with self._lock:
            self._recordings = (*self._recordings, recording)
        try:
            yield recording
        finally:
            with self._lock:
                self._recordings = tuple(r for r in self._recordings if r is not recording)

    # ---- lifetime ------------------------------------------------------------------------------
    def close(self) -> list[str]:
        """Release the sessions, the cached image BEV and the views and terms kept of the LUT (a closed detector an
        application still holds keeps none of its memory); returns the profile files written (``enable_profiling``;
        else none). Any later call that runs a graph raises DetectorClosed; a second close returns []."""
        with self._lock:  # an open detector always holds its slice graph's session: none left means closed
            sessions, self._sessions = self._sessions, {}
            self._drop_images_locked(self._image_seq)  # and an update under way installs nothing
            self._blank_bev = None
        self._views.close()
        written = [s.end_profiling() for s in sessions.values()] if self.config.enable_profiling else []
        self.image_encoder = self.lifter = self.slice_head = None
        if self._terms is not None:  # kept, closed: a lift under way raises DetectorClosed at its next graph run
            self._terms.close(self._closed_error())
        if self._fallback is not None:
            self._fallback = dataclasses.replace(self._fallback, session=None)
        del sessions
        release_free_memory()  # the sessions' arenas and the image BEV, freed above: handed back, not kept mapped
        return written

    def _closed_error(self) -> DetectorClosed:
        return DetectorClosed(f"{self.export_dir}: the detector was closed; make a new StreamingDetector")

    def __enter__(self) -> "StreamingDetector":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _recordings_of(ref: weakref.ref) -> Callable[[], tuple[GraphRecording, ...]]:
    """The recording() blocks open on the detector ``ref`` names (none once it is gone), for its CameraTerms: a
    reference back to the detector would be a cycle that keeps a closed one alive until a full collection (heap.py)."""

    def recordings() -> tuple[GraphRecording, ...]:
        det = ref()
        return () if det is None else det._recordings

    return recordings


def _gave_up(seq: int) -> bool:
    """False (nothing installed) for an update that saw more calibration swaps than MAX_RELIFTS_PER_UPDATE."""
    log.warning("update_images: the calibration was swapped more than %d times during image update %d; its images are "
                "given up (the next update lifts with the LUT then in use)", MAX_RELIFTS_PER_UPDATE, seq)
    return False


def _restamp(state: QuadrantState, qlut: QuadrantLut) -> float:
    """The timestamp of ``state`` re-lifted with ``qlut``: from the cameras that LUT reads (quadrant_timestamp)."""
    if not state.camera_timestamps:
        return state.timestamp
    update_ts = state.timestamp if state.update_timestamp is None else state.update_timestamp
    return quadrant_timestamp(qlut.camera_names, dict(state.camera_timestamps), state.feature_cameras, update_ts)


def _frozen_copy(a: np.ndarray) -> np.ndarray:
    """A read-only copy of ``a``: nobody, the caller included, can change it under the object's identity."""
    out = np.array(a, dtype=np.float32, copy=True)
    out.setflags(write=False)
    return out
