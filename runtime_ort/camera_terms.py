"""Per-camera lifts: a quadrant update that recomputes only the cameras whose frames changed.

The phase-locked image lane (``phase_locked_lane.py``) lifts a quadrant again whenever one of its cameras sends a
new frame (LiDAR-synchronised cameras fire one after the other), and the lifter graph gathers every camera's slots
each time. With the flat lifter, a quadrant's pre-activation map is the first convolution's bias plus one **term**
per camera (``lifter_split.py``, ``calibration/camera_lut.py``): ``CameraTerms`` keeps the newest term of every
(quadrant, camera), computes a camera's terms when its frame is encoded (``prepare``), and a quadrant update is then
the tail graph: the terms scattered into the quadrant's cells and added to the bias, then the rest of the lifter
(all in onnxruntime, which releases the GIL: numpy work here measurably delayed the slice lane). What it saves
and costs is measured in docs/replay.md ("Per-camera lifts in the runtime").

A camera's term is computed with the first convolution applied *before* the gather (``lifter_split.term_graph``:
the map's rows times the convolution's weight block of each height, then the share's Z * S slots of that projected
table summed with their weights, as one sparse-times-dense product of the share's weights kept as a sparse matrix,
``sparse_lut_value``, made once per set of shares; the dense Gather form where this onnxruntime has no sparse
tensors), one onnxruntime run per camera frame for all the quadrants it feeds (``prepare``), and only for a share's
**distinct** rows (``distinct_rows``: cells far from a camera read the same pixels; the tail graph gathers each
cell's term from them).

Precision: the terms are fp32; the tail is cut from the lane's own lifter graph (fp32 or int8). With an int8 image lane the sum is
therefore quantized once, at the tail's input, instead of the int8 lifter's quantized gather and weights: the BEV
differs from the int8 lifter's by about the int8 lifter's own error (tests/test_camera_terms.py). fp16 image lanes
are not split.

A term is cached under the feature map object it was made from and the LUT it was made with: a new frame (a new
array) or a calibration swap (a new LUT) makes it again. ``DetectorConfig.camera_terms`` chooses: None (default)
uses per-camera lifts where the export's lifter splits and the lane is fp32 or int8, True requires them, False never
uses them (every quadrant update runs the lifter graph).
"""

from __future__ import annotations

import dataclasses
import logging
import threading
from contextlib import nullcontext
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Mapping

import numpy as np
import onnx
import onnxruntime as ort

from streamdet.calibration.camera_lut import CameraLut, camera_luts
from streamdet.calibration.quadrant_lut import QuadrantLut
from streamdet.runtime_ort.lifter_split import SplitError, first_conv, first_conv_output, sparse_lut, tail_graph, term_graph
from streamdet.runtime_ort.recording import Feeds, GraphRecording
from streamdet.runtime_ort.sessions import (
    CPU_PROVIDER, ORT_ERRORS, GraphRunError, SessionConfig, graph_run_error, ort_message, ort_session, resolve_providers,
)
from streamdet.runtime_ort.stats import LatencyStats

log = logging.getLogger(__name__)

SPLIT_PRECISIONS = ("fp32", "int8")  # image-lane precisions whose lifter is split
PARITY_RTOL = 1e-4  # fp32 pieces against the fp32 lifter, max |diff| relative to the output's range (float order only)
# the same on an accelerator: its fp32 GEMMs and convolutions run in TF32 by default (CUDA, TensorRT), whose 10-bit
# mantissa alone differs by about 1e-3 of the range
ACCELERATOR_PARITY_RTOL = 5e-3
# The two graphs' names in a detector's recordings (StreamingDetector.recording) and in their errors: they are cut
# from the lifter in memory, so no export file names them
TERM_GRAPH = "lifter_term"
TAIL_GRAPH = "lifter_tail"


def _no_recordings() -> tuple[GraphRecording, ...]:
    return ()


def _ort_run(graph: str, run: Callable[[], np.ndarray]) -> np.ndarray:
    """``run()``, onnxruntime's failure in it raised as the GraphRunError that the detector's other graph runs raise
    (GraphSession.run): a caller catching it on the image lane must not learn the export's lifter form first."""
    try:
        return run()
    except ORT_ERRORS as e:
        raise graph_run_error(f"{graph} (volumetric_lifter split into per-camera terms)", e) from None


def share_slots(share: CameraLut, cells_per_map: int) -> tuple[np.ndarray, np.ndarray]:
    """A share's (N, Z * S) rows of ``term_graph``'s projected table (height z's block starts at
    ``z * (cells_per_map + 1)``) and their weights."""
    n, z, s = share.index.shape
    offset = (np.arange(z, dtype=np.int64) * (cells_per_map + 1))[None, :, None]  # (1, Z, 1)
    return (share.index + offset).reshape(n, z * s), share.weight.reshape(n, z * s)


def distinct_rows(slots: np.ndarray, weights: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(slots (U, J), weights (U, J), inverse (N,)) of the distinct (slots, weights) rows of a share, so that row n's
    term is term ``inverse[n]``. Neighbouring BEV cells far from a camera read the same pixels: about half of a
    share's rows repeat one another on the nuScenes rig, and the term graph's cost is per row."""
    if slots.shape[0] == 0:
        return slots, weights, np.zeros((0,), np.int64)
    bits = np.ascontiguousarray(weights, dtype=np.float32).view(np.int32)  # exact float bits: -0.0 is not 0.0
    key = np.concatenate([slots.astype(np.int64), bits.astype(np.int64)], axis=1)  # (N, 2J)
    _, first, inverse = np.unique(key, axis=0, return_index=True, return_inverse=True)
    return slots[first], weights[first], inverse.reshape(-1).astype(np.int64)


def stack_rows(slots: tuple[np.ndarray, ...], weights: tuple[np.ndarray, ...], pad_row: int) -> tuple[np.ndarray, np.ndarray]:
    """The (U, J) slots and weights of several shares of one camera, stacked row-wise for one term run. A share is
    Z * S slots wide, S the most slots the camera holds in one voxel of that quadrant, so one camera's shares differ
    in width where it barely reaches a quadrant (a camera that sees a few cells of a neighbouring quadrant at one
    height, two elsewhere): the narrower ones are padded with zero-weight slots of ``pad_row``, which add nothing
    (the sparse LUT leaves them out; the dense gather multiplies that row by 0)."""
    if len(slots) == 1:
        return slots[0], weights[0]
    width = max(s.shape[1] for s in slots)
    if all(s.shape[1] == width for s in slots):  # the usual case: one concatenation each
        return np.concatenate(slots), np.concatenate(weights)
    out_slots = np.full((sum(s.shape[0] for s in slots), width), pad_row, slots[0].dtype)  # (U, J)
    out_weights = np.zeros(out_slots.shape, weights[0].dtype)
    start = 0
    for s, w in zip(slots, weights):
        out_slots[start : start + s.shape[0], : s.shape[1]] = s
        out_weights[start : start + s.shape[0], : s.shape[1]] = w
        start += s.shape[0]
    return out_slots, out_weights


def sparse_lut_value(slots: np.ndarray, weights: np.ndarray, table_rows: int) -> ort.OrtValue:
    """``lifter_split.sparse_lut`` of (N, J) slots and weights as the (N, table_rows) COO sparse OrtValue that the
    sparse ``term_graph`` takes (CPU memory; the value keeps its arrays alive)."""
    values, coo = sparse_lut(slots, weights, table_rows)
    shape = np.array([slots.shape[0], table_rows], np.int64)
    tensor = ort.SparseTensor.sparse_coo_from_numpy(shape, values, coo, ort.OrtDevice.make("cpu", 0))
    return ort.OrtValue.ort_value_from_sparse_tensor(tensor)


@dataclass(frozen=True, eq=False)
class _Share:
    share: CameraLut
    slots: np.ndarray  # (U, Z * S) rows of term_graph's projected table, the share's distinct rows
    weights: np.ndarray  # (U, Z * S)
    inverse: np.ndarray  # (N,) the distinct row of each of the share's cells


def _share(share: CameraLut, cells_per_map: int) -> _Share:
    return _Share(share, *distinct_rows(*share_slots(share, cells_per_map)))


class CameraTerms:
    """Per-camera partial lifts of one export's flat lifter, and the newest term of every (quadrant, camera)."""

    def __init__(self, fp32_lifter: onnx.ModelProto, lane_lifter: onnx.ModelProto, channels: int,
                 feature_hw: tuple[int, int], quadrant_hw: tuple[int, int], heights: int, session: SessionConfig,
                 stats: LatencyStats | None = None) -> None:  # fmt: skip
        """``fp32_lifter``: the export's fp32 lifter graph (the first convolution's fp32 weight and bias);
        ``lane_lifter``: the lifter graph of the image lane's precision (the tail is cut from it); ``heights``: the
        LUT's z planes."""
        conv, weight, bias = first_conv(fp32_lifter)
        cut = conv.output[0] if lane_lifter is fp32_lifter else first_conv_output(lane_lifter)
        self.channels = int(channels)
        self.feature_hw = (int(feature_hw[0]), int(feature_hw[1]))
        self.quadrant_hw = (int(quadrant_hw[0]), int(quadrant_hw[1]))
        self.bias = bias  # (C_out,)
        self._table_rows = heights * (self.feature_hw[0] * self.feature_hw[1] + 1)
        self._term_graph, self.sparse = self._open_term_graph(weight, heights, session)
        # One intra-op thread for the tail whatever the lane's: onnxruntime's ScatterND with reduction "add" splits its
        # updates over the threads without a lock, and cells seen by two cameras then lose one camera's term now and
        # then (measured: 1.4 % of the output range apart within 50 repeats of one quadrant with 2 threads).
        tail_session = dataclasses.replace(session, intra_op_threads=1)
        self._tail = ort_session(tail_graph(lane_lifter, cut, (weight.shape[0], *self.quadrant_hw), bias).SerializeToString(), tail_session)
        self._stats = stats
        # the recordings open now (the detector's recording() blocks), read when a run starts, as the detector's own
        # runs read them: set by the detector that holds these terms (weakly: no cycle keeps a closed detector alive)
        self.recordings: Callable[[], tuple[GraphRecording, ...]] = _no_recordings
        self._closed: BaseException | None = None  # close(): raised by every later graph run
        self._lock = threading.Lock()
        self._shares: dict[int, tuple[QuadrantLut, tuple[_Share, ...]]] = {}  # id(qlut) -> (qlut, its shares)
        self._terms: dict[tuple[int, str], tuple[object, object, np.ndarray]] = {}  # (q, cam) -> (source, qlut, term)
        self._luts: dict[tuple[int, ...], tuple[tuple[_Share, ...], object]] = {}  # share ids -> (shares, sparse lut)

    def _open_term_graph(self, weight: np.ndarray, heights: int, session: SessionConfig) -> tuple[ort.InferenceSession, bool]:
        """(session, sparse): the sparse term graph where the sessions run on the CPU alone and this onnxruntime runs
        it (its SparseToDenseMatMul and sparse tensors, tried once on a one-row LUT), else the dense one (an
        accelerator provider has no SparseToDenseMatMul kernel: the dense form keeps the whole graph on it)."""
        providers = resolve_providers(session.providers)
        if providers != [CPU_PROVIDER]:
            log.info("per-camera terms: the dense term graph (providers %s)", providers)
        else:
            try:
                graph = ort_session(term_graph(weight, self.channels, self.feature_hw, heights, sparse=True).SerializeToString(), session)
                probe = sparse_lut_value(np.zeros((1, 1), np.int64), np.ones((1, 1), np.float32), self._table_rows)
                features = ort.OrtValue.ortvalue_from_numpy(np.zeros((1, self.channels, *self.feature_hw), np.float32))
                graph.run_with_ort_values(["term"], {"features": features, "lut": probe})
                return graph, True
            except (*ORT_ERRORS, AttributeError, RuntimeError) as e:  # a build without contrib ops or sparse tensors
                log.info("per-camera terms: the dense term graph (the sparse one does not run here: %s)", ort_message(e))
        return ort_session(term_graph(weight, self.channels, self.feature_hw, heights, sparse=False).SerializeToString(), session), False

    def _sparse_lut(self, shares: tuple[_Share, ...]):
        """The sparse LUT of these shares' distinct rows in this order, made once and kept while their quadrant LUTs'
        shares are (``shares``), at most 64."""
        key = tuple(id(s) for s in shares)
        with self._lock:
            cached = self._luts.get(key)
        if cached is not None and all(a is b for a, b in zip(cached[0], shares)):
            return cached[1]
        value = sparse_lut_value(*self._stacked(shares), self._table_rows)
        with self._lock:
            if self._closed is not None:  # closed meanwhile: a closed detector keeps nothing
                return value
            if len(self._luts) >= 64:
                self._luts.pop(next(iter(self._luts)))
            self._luts[key] = (shares, value)
        return value

    # ---- the pieces --------------------------------------------------------------------------
    def shares(self, qlut: QuadrantLut) -> tuple[_Share, ...]:
        """The camera shares of one quadrant LUT, made once per LUT object (the newest eight kept: two LUTs)."""
        with self._lock:
            cached = self._shares.get(id(qlut))
        if cached is not None and cached[0] is qlut:
            return cached[1]
        cells = self.feature_hw[0] * self.feature_hw[1]
        shares = tuple(_share(s, cells) for s in camera_luts(qlut, cells))
        with self._lock:
            if self._closed is not None:
                return shares
            if len(self._shares) >= 8:
                _, gone = self._shares.pop(next(iter(self._shares)))
                gone_ids = {id(s) for s in gone}  # their sparse LUTs go with them
                self._luts = {k: v for k, v in self._luts.items() if not gone_ids.intersection(k)}
            self._shares[id(qlut)] = (qlut, shares)
        return shares

    def warm(self, qluts: tuple[QuadrantLut, ...]) -> None:
        """Make what the lifts of ``qluts`` (one LUT's four quadrants) will need ahead of them: each quadrant's
        camera shares and, with the sparse term graph, each camera's sparse LUT over all its quadrants (``prepare``'s
        run) and each share's own (a lift whose frame was not prepared). Building them for a new LUT takes longer than
        an image update (docs/replay.md): a caller swapping the calibration pays it, not the image lane."""
        by_camera: dict[str, list[_Share]] = {}
        for qlut in qluts:
            for s in self.shares(qlut):
                by_camera.setdefault(s.share.camera_name, []).append(s)
                if self.sparse:
                    self._sparse_lut((s,))
        if self.sparse:
            for shares in by_camera.values():
                if len(shares) > 1:
                    self._sparse_lut(tuple(shares))

    def term(self, features: np.ndarray, share: _Share) -> np.ndarray:
        """(U, C_out) distinct terms of one camera share from that camera's (C, Hf, Wf) float32 feature map."""
        return self.terms(features, (share,))[0]

    def terms(self, features: np.ndarray, shares: tuple[_Share, ...]) -> tuple[np.ndarray, ...]:
        """The distinct terms of several shares of one camera (its quadrants), one run: the map projected once."""
        with self._timed("lifter_partial"):
            return self._run_terms(features, shares)

    def close(self, error: BaseException) -> None:
        """Release the term and tail sessions; every later run raises ``error`` (the detector's DetectorClosed). A
        run already under way keeps its session until it returns, and nothing is kept from then on."""
        self._term_graph = self._tail = None
        with self._lock:  # the kept terms and tables (about a hundred MB at the default size) go now, not with the detector
            self._closed = error
            self._shares, self._terms, self._luts = {}, {}, {}

    def _session(self, session: ort.InferenceSession | None) -> ort.InferenceSession:
        if session is None:  # closed: set before the sessions were released
            raise type(self._closed)(*self._closed.args)
        return session

    def _stacked(self, shares: tuple[_Share, ...] | list[_Share]) -> tuple[np.ndarray, np.ndarray]:
        """``stack_rows`` of these shares' distinct rows, padded with height 0's zero row (the sentinel)."""
        pad_row = self.feature_hw[0] * self.feature_hw[1]
        return stack_rows(tuple(s.slots for s in shares), tuple(s.weights for s in shares), pad_row)

    def _run_terms(self, features: np.ndarray, shares: tuple[_Share, ...]) -> tuple[np.ndarray, ...]:
        sizes = [s.slots.shape[0] for s in shares]
        if sum(sizes) == 0:  # a camera the LUT lists in the quadrant but that reads no cell there
            return tuple(np.zeros((0, self.bias.size), np.float32) for _ in shares)
        graph = self._session(self._term_graph)  # one read: close() may release it meanwhile
        recordings = self.recordings()
        rows = None
        if self.sparse:  # the rows are stacked only where the sparse LUT of these shares is not kept yet
            feeds = {"features": ort.OrtValue.ortvalue_from_numpy(np.ascontiguousarray(features[None])),
                     "lut": self._sparse_lut(tuple(shares))}  # fmt: skip
            out = _ort_run(TERM_GRAPH, lambda: graph.run_with_ort_values(["term"], feeds)[0].numpy())  # (U, C_out)
        else:
            rows = self._stacked(shares)  # (U, J) slots and weights
            dense = {"features": features[None], "slots": rows[0], "weights": rows[1]}
            out = _ort_run(TERM_GRAPH, lambda: graph.run(None, dense)[0])  # (U, C_out)
        if recordings:
            # the dense term graph's feeds whichever form ran: a sparse OrtValue is no array, and the rows define it
            slots, weights = self._stacked(shares) if rows is None else rows
            for recording in recordings:
                recording.add(TERM_GRAPH, {"features": features[None], "slots": slots, "weights": weights}, (out,))
        return tuple(np.split(out, np.cumsum(sizes)[:-1]))

    def tail_feeds(self, shares: tuple[_Share, ...], terms: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
        """The tail graph's feeds: the given cameras' distinct terms, the term of each of their cells and those
        cells, concatenated in the shares' order."""
        given = [s for s in shares if s.share.camera_name in terms]
        if not given:  # none of the quadrant's cameras: the bias alone
            return {"terms": np.zeros((0, self.bias.size), np.float32), "rows": np.zeros((0,), np.int64),
                    "cells": np.zeros((0, 1), np.int64)}  # fmt: skip
        stacked = np.concatenate([terms[s.share.camera_name] for s in given])  # (U, C_out)
        offsets = np.cumsum([0] + [s.slots.shape[0] for s in given[:-1]])
        rows = np.concatenate([s.inverse + o for s, o in zip(given, offsets)])  # (M,)
        return {"terms": stacked, "rows": rows, "cells": np.concatenate([s.share.cells for s in given])[:, None]}  # (M, 1)

    def tail(self, feeds: Mapping[str, np.ndarray]) -> np.ndarray:
        session = self._session(self._tail)
        recordings = self.recordings()
        given: Feeds = dict(feeds)
        out = _ort_run(TAIL_GRAPH, lambda: session.run(None, given)[0])  # (1, C, Yq, Xq)
        for recording in recordings:
            recording.add(TAIL_GRAPH, given, (out,))
        return out

    # ---- the cache ---------------------------------------------------------------------------
    def prepare(self, qluts: tuple[QuadrantLut, ...], maps: Mapping[str, np.ndarray]) -> int:
        """Compute and keep the terms of these (C, Hf, Wf) feature maps (by camera) in every quadrant of ``qluts``
        their camera feeds, keyed by the map object. The number of terms computed."""
        wanted: dict[str, list[tuple[int, QuadrantLut, _Share]]] = {}  # camera -> its shares whose term is not kept
        for q, qlut in enumerate(qluts):
            for s in self.shares(qlut):
                name = s.share.camera_name
                if name in maps and self._kept(q, qlut, s, maps[name]) is None:
                    wanted.setdefault(name, []).append((q, qlut, s))
        for name, entries in wanted.items():  # one run per camera over all its quadrants
            made = self.terms(maps[name], tuple(s for _, _, s in entries))
            with self._lock:
                for (q, qlut, s), term in zip(entries, made):
                    if self._closed is None:
                        self._terms[(q, name)] = (maps[name], qlut, term)
        return sum(len(entries) for entries in wanted.values())

    def lift(self, quadrant: int, qlut: QuadrantLut, maps: Mapping[str, np.ndarray]) -> np.ndarray:
        """The lifter's output for ``quadrant`` (its LUT ``qlut``) from the (C, Hf, Wf) maps of the cameras given
        (a camera not given contributes nothing, as a zero feature map does): cached terms where the map object is
        the one a term was made from, new terms (then kept) otherwise."""
        shares = self.shares(qlut)
        terms = {s.share.camera_name: self._term_of(quadrant, qlut, s, maps[s.share.camera_name])[0]
                 for s in shares if s.share.camera_name in maps}  # fmt: skip
        with self._timed("lifter_tail"):
            return self.tail(self.tail_feeds(shares, terms))

    def _term_of(self, q: int, qlut: QuadrantLut, share: _Share, features: np.ndarray) -> tuple[np.ndarray, bool]:
        """(term, whether it was made now): the kept term of (q, camera) if it was made from this map object and
        LUT, else a new one, kept (the entry holds the map and LUT, so their ids cannot be reused while it lives)."""
        kept = self._kept(q, qlut, share, features)
        if kept is not None:
            return kept, False
        term = self.term(features, share)
        with self._lock:
            if self._closed is None:
                self._terms[(q, share.share.camera_name)] = (features, qlut, term)
        return term, True

    def _kept(self, q: int, qlut: QuadrantLut, share: _Share, features: np.ndarray) -> np.ndarray | None:
        """The kept term of (q, camera) if it was made from this map object and LUT; else None."""
        with self._lock:
            entry = self._terms.get((q, share.share.camera_name))
        return entry[2] if entry is not None and entry[0] is features and entry[1] is qlut else None

    def _timed(self, stage: str):
        return nullcontext() if self._stats is None else self._stats.time(stage)

    def check(self, fp32_lifter_run, qluts: tuple[QuadrantLut, ...], fp32_tail: "CameraTerms") -> float:
        """Max |diff| / output range of this split's terms with ``fp32_tail``'s tail (the fp32 one) against
        ``fp32_lifter_run(qlut, maps)`` (the export's fp32 lifter) on seeded random feature maps, over the quadrants
        some camera sees."""
        rng = np.random.default_rng(0)
        worst = 0.0
        for qlut in qluts:
            if not qlut.camera_names:
                continue
            maps = rng.standard_normal((len(qlut.camera_names), self.channels, *self.feature_hw)).astype(np.float32)
            ref = fp32_lifter_run(qlut, maps)
            shares = self.shares(qlut)
            terms = {s.share.camera_name: self._run_terms(maps[qlut.camera_names.index(s.share.camera_name)], (s,))[0] for s in shares}
            got = fp32_tail.tail(self.tail_feeds(shares, terms))
            worst = max(worst, float(np.abs(got - ref).max() / max(float(np.ptp(ref)), 1e-6)))
        return worst


def open_camera_terms(
    export_dir: Path, lifter_form: str, lifter_model: Callable[[str], onnx.ModelProto], lane_precision: str, mode: bool | None, channels: int,
    feature_hw: tuple[int, int], quadrant_hw: tuple[int, int], session: SessionConfig, stats: LatencyStats | None,
    fp32_lifter_run, qluts: tuple[QuadrantLut, ...],
) -> CameraTerms | None:  # fmt: skip
    """The per-camera lifts of an export, checked against its fp32 lifter; None where ``mode`` is None (auto) and
    the export's lifter does not split (``lifter_form``, the manifest's, is not "flat", or the lane is fp16, or the
    graph does not cut), or where ``mode`` is False. ``mode`` True and no split:
    ValueError saying why. ``lifter_model(precision)``: the export's lifter graph of that precision, read and checked
    (``manifest.read_export_file``, graph_files.py); ``fp32_lifter_run(qlut, maps)``:
    the export's fp32 lifter on one quadrant (the check's reference)."""
    if mode is False:
        return None
    why = None
    failed = False  # a split that fails its check or does not run: news, where a form or precision without one is not
    if lifter_form != "flat":
        why = f"its lifter is the {lifter_form!r} form: a per-camera lift needs the flat lifter (LifterConfig.form='flat')"
    elif lane_precision not in SPLIT_PRECISIONS:
        why = f"the {lane_precision} image lane's lifter is not split (only {list(SPLIT_PRECISIONS)})"
    else:
        heights = int(qluts[0].index.shape[2])  # (1, K, Z, Yq, Xq)
        try:
            fp32 = lifter_model("fp32")
            lane = fp32 if lane_precision == "fp32" else lifter_model(lane_precision)
            terms = CameraTerms(fp32, lane, channels, feature_hw, quadrant_hw, heights, session, stats)
            fp32_tail = terms if lane is fp32 else CameraTerms(fp32, fp32, channels, feature_hw, quadrant_hw, heights, session)
            err = terms.check(fp32_lifter_run, qluts, fp32_tail)
            rtol = PARITY_RTOL if resolve_providers(session.providers) == [CPU_PROVIDER] else ACCELERATOR_PARITY_RTOL
            if not err <= rtol:
                why = f"its per-camera pieces differ from the fp32 lifter by {err:.2e} of the output range (> {rtol})"
                failed = True
        except SplitError as e:
            why = str(e)
        except (*ORT_ERRORS, GraphRunError) as e:  # a cut that onnxruntime cannot run is not a split
            why, failed = f"its per-camera pieces do not run: {ort_message(e)}", True
    if why is None:
        log.info("%s: per-camera lifts for image updates (%s tail, %s terms)", export_dir, lane_precision,
                 "sparse" if terms.sparse else "dense")  # fmt: skip
        terms.warm(qluts)
        return terms
    if mode is True:
        raise ValueError(f"{export_dir}: DetectorConfig.camera_terms=True, but {why}")
    (log.warning if failed else log.info)("%s: no per-camera lifts: %s", export_dir, why)
    return None
