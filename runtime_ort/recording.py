"""What a ``StreamingDetector`` feeds its graphs, recorded: every onnxruntime run's graph, feeds and outputs.

``StreamingDetector.recording()`` yields a ``GraphRecording`` that collects each graph run the detector makes
while the block runs, in call order, from any thread: the exact feed dicts it hands its sessions (images batch,
feature maps with the LUT, pillar tensors with the cached image BEV or the quadrant ids) and what they returned.
With per-camera lifts (``runtime_ort/camera_terms.py``, on by default for a flat-lifter export) an image update runs
the two graphs cut from the lifter instead of ``volumetric_lifter``: ``lifter_term`` (a camera's feature map and its
share of the LUT as the dense term graph's slots and weights, whichever form ran) and ``lifter_tail``.

For tools that need the runtime's real graph inputs without building them a second time: the exporter calibrates
its int8 graphs on the feeds the fp32 detector recorded over real samples, and runs its whole-pipeline parity
checks by running the detector at two precisions on the same data (export/int8_steps.py, export/graph_steps.py).
Nothing is copied: the detector never changes an array after handing it to a session, so a recording holds the
arrays themselves (and keeps them alive as long as it lives).
"""

from __future__ import annotations

import threading
from dataclasses import dataclass

import numpy as np

Feeds = dict[str, np.ndarray]


@dataclass(frozen=True, eq=False)
class GraphRun:
    """One onnxruntime run of one of the detector's graphs."""

    # "image_encoder", "volumetric_lifter", "slice_head", "slice_head_fallback"; "lifter_term" and "lifter_tail" with
    # per-camera lifts
    graph: str
    feeds: Feeds  # input name -> the array the session was given
    outputs: tuple[np.ndarray, ...]  # in the graph's output order


class GraphRecording:
    """The graph runs of a detector while a ``StreamingDetector.recording()`` block runs, in call order."""

    def __init__(self) -> None:
        self._runs: list[GraphRun] = []
        self._lock = threading.Lock()  # the two lanes may record at the same time

    def add(self, graph: str, feeds: Feeds, outputs: list[np.ndarray] | tuple[np.ndarray, ...]) -> None:
        run = GraphRun(graph, dict(feeds), tuple(outputs))
        with self._lock:
            self._runs.append(run)

    @property
    def runs(self) -> tuple[GraphRun, ...]:
        with self._lock:
            return tuple(self._runs)

    def of(self, graph: str) -> list[GraphRun]:
        """The runs of ``graph``, in call order."""
        return [r for r in self.runs if r.graph == graph]

    def feeds(self, graph: str) -> list[Feeds]:
        """The feed dicts ``graph`` was run with, in call order."""
        return [r.feeds for r in self.of(graph)]

    def outputs(self, graph: str) -> list[tuple[np.ndarray, ...]]:
        """What ``graph`` returned, run by run."""
        return [r.outputs for r in self.of(graph)]

    def __len__(self) -> int:
        with self._lock:
            return len(self._runs)
