"""The LiDAR-only fallback of a camera + LiDAR detector: slices without usable camera features run a LiDAR-only
export's slice graph instead (``DetectorConfig.fallback_export_dir``).

Why: a fused model trained with its cameras on from the first step can lean on them so much that it finds almost
nothing when they are gone (issue 19's class-loss model detected almost nothing with every camera zeroed; measured:
docs/training/issue19_plan.md, section "Fifth session (2026-12-02, fourth): `small_v3` (item 2) and an image-side
class loss (item 1)"). A vehicle process must not go blind with its cameras, so the detector can hold a
LiDAR-only slice graph (the shipped ``small_lidar_only.pt`` exported) and use it for a slice when

- a quadrant the slice reads has **no image BEV** (no image update yet, a calibration swap without re-lift, or an
  image update given none of that quadrant's cameras: ``ImageUpdate.cleared``), or
- with ``fallback_after_s``, the oldest image BEV it reads is **older** than that at the slice's timestamp (the
  image lane stopped, or fell that far behind).

A camera that fails alone is not a fallback case: its features are zeros in the next updates and the other cameras
still reach the BEV (``ImageUpdate.cameras_missing`` says so). ``SliceResult.fallback`` tells which graph ran.

The fallback export must be LiDAR-only and share the main export's grid, classes and pillar limits (the slice's
pillars are made once, for whichever graph runs); its post-processing is the main detector's.
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path

from streamdet.calibration.grid import GridSpec
from streamdet.runtime_ort.graph_files import checked_model
from streamdet.runtime_ort.manifest import GraphEntry, Manifest, ManifestError, read_export_file, read_manifest
from streamdet.runtime_ort.sessions import GraphSession, SessionConfig
from streamdet.runtime_ort.signature import check_graph, check_runtime_fields

FALLBACK_GRAPH = "slice_head_fallback"  # its name in the detector's sessions, stats and recordings


@dataclass(frozen=True, eq=False)
class LidarFallback:
    """A LiDAR-only export's slice graph, opened beside a fused export's."""

    export_dir: Path
    manifest: Manifest
    session: GraphSession | None  # None once the detector that opened it was closed
    entry: GraphEntry  # the manifest's entry of the graph in use (its MAC count)
    slice_crop: bool  # False: a LiDAR-only net without the quadrant crop (one whole-grid map per slice)


def check_fallback_age(after_s: float | None, export_dir: object) -> None:
    """ValueError unless ``after_s`` is None or a finite number of seconds >= 0, and only set with a fallback."""
    if after_s is None:
        return
    if isinstance(after_s, bool) or not isinstance(after_s, numbers.Real) or not math.isfinite(after_s) or after_s < 0:
        raise ValueError(f"DetectorConfig.fallback_after_s must be None or a finite number of seconds >= 0, got {after_s!r}")
    if export_dir is None:
        raise ValueError("DetectorConfig.fallback_after_s needs a fallback_export_dir (a LiDAR-only export) to fall back to")


def open_fallback(export_dir: str | Path, main: Manifest, grid: GridSpec, session_config: SessionConfig,
                  precision: str, verify_sha256: bool,
                  provider_options: Callable[[GraphEntry], Mapping[str, Mapping[str, str]]] | None = None) -> LidarFallback:  # fmt: skip
    """The slice graph of the LiDAR-only export at ``export_dir``, checked against the main export ``main``;
    ``provider_options``: the session's provider options for the graph's manifest entry (GraphSession)."""
    path = Path(export_dir)
    m = read_manifest(path, verify_files=verify_sha256)
    check_runtime_fields(m)
    where = f"fallback export {path}"
    if m.use_image:
        raise ValueError(f"{where} has an image lane: the fallback must be a LiDAR-only export (preset use_image=false)")
    try:
        fb_grid = GridSpec.from_dict(m.grid)
    except (ValueError, TypeError) as e:
        raise ManifestError(f"{path / 'manifest.json'}: grid: {e}") from None
    if fb_grid != grid:
        raise ValueError(f"{where} has another grid than the detector's: {m.grid} vs {main.grid}")
    if tuple(m.class_names) != tuple(main.class_names):
        raise ValueError(f"{where} has other classes than the detector's: {list(m.class_names)} vs {list(main.class_names)}")
    for key in ("max_points_per_pillar", "max_pillars"):
        if int(m.preset["pillars"][key]) != int(main.preset["pillars"][key]):
            raise ValueError(f"{where}: pillars.{key} is {m.preset['pillars'][key]}, the detector's "
                             f"{main.preset['pillars'][key]} (one set of pillars feeds either graph)")  # fmt: skip
    if precision not in m.precisions:
        raise ValueError(f"{where} has no {precision} graphs (it has {list(m.precisions)}; DetectorConfig.precision)")
    entry = m.graph("slice_head", precision)
    file, raw = read_export_file(path, entry, f"graph file of slice_head ({precision})", verify_sha256)
    checked_model(file, raw, entry)
    options = None if provider_options is None else provider_options(entry)
    graph = GraphSession(file, session_config, model=raw, provider_options=options)  # the bytes hashed are the bytes loaded
    check_graph(entry, graph.inputs, graph.outputs, m, fb_grid)
    return LidarFallback(path, m, graph, entry, m.slice_crop)


# An image BEV stamped more than this after the slice it would be fused with: the caller's image and slice clocks
# disagree (a clock that jumped, two clocks never aligned), so the image's age is unknown. Frames newer than the scan
# by up to a camera period are normal (the phase-locked lane lifts them); seconds are not.
CLOCKS_APART_S = 1.0
# An image BEV older than this at its slice's timestamp is far more likely two clocks read as one (an epoch stamp
# against time.monotonic(), nanoseconds against seconds) than an image lane stopped for an hour. Past it, or stamped
# over CLOCKS_APART_S after the slice, the detector logs both timestamps once (StreamingDetector._warn_clocks),
# with a fallback or without.
IMPLAUSIBLE_IMAGE_AGE_S = 3600.0


def needs_fallback(has_every_quadrant: bool, image_age_s: float | None, after_s: float | None) -> bool:
    """Whether a slice runs the fallback: a quadrant it reads has no image BEV, or (``after_s`` set) the oldest it
    reads is older than ``after_s`` seconds, or of unknown age: stamped more than CLOCKS_APART_S after the slice
    (a stale image behind a forward clock jump fused for ever before)."""
    if not has_every_quadrant or image_age_s is None:
        return True
    return after_s is not None and (image_age_s > after_s or image_age_s < -CLOCKS_APART_S)
