"""Opening and verifying an export for `StreamingDetector` (runtime_ort/detector.py): everything its construction
checks and opens before the first image or slice.

`open_export` reads the manifest (or takes the exporter's staged one), checks it against what the runtime feeds and
against the ``DetectorConfig``, opens and checks a session per graph in use (and the LiDAR-only fallback's), loads
or builds the projection LUT and opens the per-camera lifts. It returns what it opened as one `OpenedExport`; the
detector keeps those as its attributes. Any defect raises before the detector exists (README, "Trust and failure
model": start-up verifies everything), in the order the checks are listed in `open_export`.

The LUT checks and the LUT build live here too because ``set_calibration`` runs the same ones on every new
calibration (``StreamingDetector._check_lut`` / ``_build_lut`` call them).
"""

from __future__ import annotations

import dataclasses
import logging
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import onnx

from streamdet.calibration.camera import CalibrationError, Rig
from streamdet.calibration.grid import GridSpec
from streamdet.calibration.lut import BlindCameraWarning, Lut, blind_cameras, check_rig_fits
from streamdet.calibration.lut_build import build_lut
from streamdet.calibration.quadrant_lut import QuadrantLut
from streamdet.core.sectors import NUM_QUADRANTS, check_num_slices, quadrants_of_sector
from streamdet.runtime_ort.camera_terms import CameraTerms, open_camera_terms
from streamdet.runtime_ort.detector_config import DetectorConfig, NoImageLaneError
from streamdet.runtime_ort.export_settings import export_nms, export_rig, image_spec_at
from streamdet.runtime_ort.fallback import FALLBACK_GRAPH, LidarFallback, open_fallback
from streamdet.runtime_ort.graph_files import checked_model, model_signature
from streamdet.runtime_ort.lut_views import LutViews
from streamdet.runtime_ort.manifest import GraphEntry, ImageSpec, Manifest, ManifestError, read_export_file, read_manifest
from streamdet.runtime_ort.postprocess import PostprocessConfig
from streamdet.runtime_ort.sessions import (
    TENSORRT_PROVIDER, GraphSession, ProviderError, SessionConfig, resolve_providers, without_tensorrt,
)
from streamdet.runtime_ort.signature import check_graph, check_parity, check_runtime_fields
from streamdet.runtime_ort.stats import LatencyStats
from streamdet.runtime_ort.tensorrt import default_cache_dir, tensorrt_options

# The detector's logger, not this module's: what construction logs (a blind camera) is the detector's to say, and
# applications and tests select the detector's messages by that name.
log = logging.getLogger("streamdet.runtime_ort.detector")

TYPICAL_PILLAR_SHARE = 8  # TensorRT's "opt" pillar count: the cap / this (the bundled sweep's slices hold far fewer)

# check_lut's warnings name the frame three above its caller's: the code that built the detector (check_lut <-
# open_export <- StreamingDetector.__init__ <- caller) or set_calibration (check_lut <- StreamingDetector._check_lut <-
# _swap_calibration <- set_calibration), where they pointed when the check was a method of the detector.
_LUT_WARNING_STACKLEVEL = 4
# The min_depth_m of every LUT an export runs with: export/graph_steps.py, streamdet-calib and export_lut all build
# with build_lut's default, and the model was trained on such LUTs (check_lut refuses any other).
EXPORT_LUT_MIN_DEPTH_M = 0.0


def check_profile_dir(config: DetectorConfig, export_dir: Path) -> None:
    """ValueError unless the profiles go outside every export the detector reads: the runtime writes nothing into an
    export (a file there that the manifest does not name is left alone, but an export is a unit that is copied, hashed
    and shipped whole). The default, the current directory, counts: a process started inside an export is refused."""
    target = Path(config.profile_dir if config.profile_dir is not None else ".").resolve()
    where = "DetectorConfig.profile_dir" if config.profile_dir is not None else "the profiles' default folder (the current directory)"
    for export in (export_dir, config.fallback_export_dir):
        if export is None:
            continue
        root = Path(export).resolve()
        if target == root or root in target.parents:
            raise ValueError(f"{where} {target} lies inside the export {export}: the runtime writes nothing into an "
                             f"export; give DetectorConfig.profile_dir another folder")  # fmt: skip


@dataclass(frozen=True, eq=False)
class OpenedExport:
    """What `open_export` verified and opened: the detector's attributes of the same names (underscored where
    private there). The sessions and the LUT are the detector's own from then on (``close`` releases them)."""

    config: DetectorConfig  # the caller's, with the export's NMS settings where it named none
    manifest: Manifest
    grid: GridSpec
    uses_images: bool  # False: LiDAR-only export, slice lane only
    # False: a LiDAR-only net without the quadrant crop, one whole-grid map per slice (calibration/slice_maps.py)
    slice_crop: bool
    camera_names: tuple[str, ...]
    image: ImageSpec | None  # what update_images takes; None for a LiDAR-only export
    num_slices: int
    max_points_per_pillar: int
    max_pillars: int
    post: PostprocessConfig
    # None for a LiDAR-only export: it has no image lane
    image_encoder: GraphSession | None
    lifter: GraphSession | None
    slice_head: GraphSession
    providers: tuple[str, ...]  # the slice graph's, in onnxruntime's order of preference
    fallback: LidarFallback | None
    stats: LatencyStats  # shared with the per-camera lifts, which time their runs into it
    sessions: dict[str, GraphSession]  # by graph name, the fallback's as FALLBACK_GRAPH
    graph_files: dict[str, str]  # graph name -> file name, for messages
    # The manifest's MAC counts of the graphs in use; executed_gmac scales them to each run's sizes for the stats.
    graph_entries: dict[str, GraphEntry]
    lut: Lut | None  # None for a LiDAR-only export
    built_from: tuple[Lut, str] | None  # (a LUT built here from the export's rig, the rig's sha256); None: read from lut.npz
    # per-quadrant LUTs, lifter LUT feeds and quadrant_cameras' answers, made once per LUT (lut_views.py)
    views: LutViews
    # per-camera lifts of image updates (camera_terms.py); None: every update runs the lifter graph
    terms: CameraTerms | None


def open_export(export_dir: Path, config: DetectorConfig, manifest: Manifest | None = None) -> OpenedExport:
    """Verify the export at ``export_dir`` against ``config`` and open its graphs (``StreamingDetector``'s
    construction: its docstring says what ``manifest`` is for). ManifestError for a defective export, ValueError or
    NoImageLaneError for a config it cannot run, ProviderError / CalibrationError from the sessions and the LUT."""
    if manifest is not None and not isinstance(manifest, Manifest):
        raise ValueError(f"manifest must be None or a Manifest, got {type(manifest).__name__}")
    m = manifest if manifest is not None else read_manifest(export_dir, verify_files=config.verify_sha256)
    check_runtime_fields(m)
    in_use = {"slice_head": config.precision}
    if m.use_image:
        in_use.update(image_encoder=config.image_precision, volumetric_lifter=config.image_precision)
    try:
        check_parity(m, in_use)
    except ManifestError as e:
        raise ManifestError(f"{export_dir}: {e}") from None
    try:
        grid = GridSpec.from_dict(m.grid)
    except (ValueError, TypeError) as e:
        raise ManifestError(f"{export_dir / 'manifest.json'}: grid: {e}") from None
    uses_images = m.use_image
    if not uses_images and config.image_lane_precision is not None:
        raise NoImageLaneError(
            no_image_lane(export_dir, f"DetectorConfig.image_lane_precision {config.image_lane_precision!r} cannot apply")
        )
    for what, precision in (("precision", config.precision), ("image_lane_precision", config.image_precision)):
        if precision not in m.precisions:
            raise ValueError(
                f"{export_dir} has no {precision} graphs (it has {list(m.precisions)}; DetectorConfig.{what}); "
                + (f"re-export with --{precision}" if precision != "fp32" else "the export lacks its fp32 graphs")
            )
    if not uses_images and config.image_size is not None:
        raise NoImageLaneError(no_image_lane(export_dir, f"DetectorConfig.image_size {config.image_size!r} cannot apply"))
    camera_names = tuple(m.image.camera_names) if m.image is not None else ()
    image = image_spec_at(m.image, config.image_size) if m.image is not None else None
    num_slices = int(config.num_slices) if config.num_slices is not None else m.num_slices
    try:
        check_num_slices(num_slices, config.start_deg)
    except ValueError as e:
        raise ManifestError(f"{export_dir / 'manifest.json'}: num_slices: {e}") from None
    pillars = m.preset["pillars"]
    max_points_per_pillar = int(pillars["max_points_per_pillar"])
    max_pillars = int(pillars["max_pillars"])
    if config.nms is None:
        config = dataclasses.replace(config, nms=export_nms(m))
    threshold = config.score_threshold if config.score_threshold is not None else float(m.post["score_threshold"])
    post = PostprocessConfig(score_threshold=threshold, restrict_to_sector=config.restrict_to_sector, nms=config.nms)

    if config.enable_profiling:
        check_profile_dir(config, export_dir)

    def options(entry: GraphEntry) -> dict[str, dict[str, str]] | None:
        return provider_options(entry, export_dir=export_dir, config=config, image=image, camera_names=camera_names,
                                num_slices=num_slices, max_pillars=max_pillars)  # fmt: skip

    def session(name: str, threads: int, precision: str) -> GraphSession:
        entry = m.graph(name, precision)
        path, raw, _ = read_graph(export_dir, m, name, precision, config.verify_sha256)
        cfg = SessionConfig(config.providers, threads, enable_profiling=config.enable_profiling, profile_dir=config.profile_dir)
        graph = GraphSession(path, cfg, model=raw, provider_options=options(entry))  # the bytes hashed are the bytes loaded
        check_graph(entry, graph.inputs, graph.outputs, m, grid)  # the graph is what the manifest says
        return graph

    image_lane = (config.image_lane_threads, config.image_precision)
    image_encoder = session("image_encoder", *image_lane) if uses_images else None
    lifter = session("volumetric_lifter", *image_lane) if uses_images else None
    slice_head = session("slice_head", config.slice_lane_threads, config.precision)
    fallback: LidarFallback | None = None
    if config.fallback_export_dir is not None:
        if not uses_images:
            raise NoImageLaneError(no_image_lane(export_dir, "it needs no LiDAR-only fallback (DetectorConfig.fallback_export_dir)"))
        cfg = SessionConfig(config.providers, config.slice_lane_threads, enable_profiling=config.enable_profiling,
                            profile_dir=config.profile_dir)  # fmt: skip
        fallback = open_fallback(config.fallback_export_dir, m, grid, cfg, config.precision, config.verify_sha256, options)
    stats = LatencyStats()
    graphs = {"image_encoder": image_encoder, "volumetric_lifter": lifter, "slice_head": slice_head,
              FALLBACK_GRAPH: None if fallback is None else fallback.session}  # fmt: skip
    sessions = {name: g for name, g in graphs.items() if g is not None}
    lanes = {"image_encoder": config.image_precision, "volumetric_lifter": config.image_precision, "slice_head": config.precision}
    graph_entries = {name: m.graph(name, lanes[name]) for name in m.required_graphs}
    if fallback is not None:
        graph_entries[FALLBACK_GRAPH] = fallback.entry

    lut: Lut | None = None
    built_from: tuple[Lut, str] | None = None
    if uses_images and (image.width, image.height) == (m.image.width, m.image.height):
        lut_path, raw = read_export_file(export_dir, m.lut, "lut.file", config.verify_sha256)
        loaded = Lut.load(lut_path, grid, len(camera_names), data=raw)  # headers checked first
        if loaded.calibration_sha256 != m.lut.calibration_sha256:  # streamdet-calib rewrites both together
            raise ManifestError(f"{lut_path} was built from calibration {loaded.calibration_sha256[:12]}..., the manifest "
                                f"records {m.lut.calibration_sha256[:12]}... (lut.calibration_sha256)")  # fmt: skip
        lut = check_lut(loaded, image, camera_names, grid, export_dir, m)
    elif uses_images:
        rig = export_rig(m, export_dir)
        lut = check_lut(export_lut(rig, image, camera_names, grid, m), image, camera_names, grid, export_dir, m)
        built_from = (lut, rig.sha256())
    views = LutViews(camera_names, m.lut_layout)
    terms = _open_camera_terms(export_dir, m, config, grid, image, lifter, stats, views, lut) if uses_images and lut is not None else None
    return OpenedExport(
        config=config, manifest=m, grid=grid, uses_images=uses_images, slice_crop=m.slice_crop, camera_names=camera_names,
        image=image, num_slices=num_slices, max_points_per_pillar=max_points_per_pillar, max_pillars=max_pillars, post=post,
        image_encoder=image_encoder, lifter=lifter, slice_head=slice_head, providers=slice_head.providers, fallback=fallback,
        stats=stats, sessions=sessions, graph_files={name: g.path.name for name, g in sessions.items()},
        graph_entries=graph_entries, lut=lut, built_from=built_from, views=views, terms=terms,
    )  # fmt: skip


def no_image_lane(export_dir: Path, what: str) -> str:
    """The words of every refusal a LiDAR-only export gives a call of the image lane (NoImageLaneError)."""
    return (f"{export_dir} is a LiDAR-only export (manifest preset use_image=false) with no image lane: {what}; "
            "feed its slices to detect_slice / detect_sweep only")  # fmt: skip


def provider_options(entry: GraphEntry, *, export_dir: Path, config: DetectorConfig, image: ImageSpec | None,
                     camera_names: tuple[str, ...], num_slices: int, max_pillars: int) -> dict[str, dict[str, str]] | None:  # fmt: skip
    """TensorRT's options for one graph where TensorRT is among the providers (runtime_ort/tensorrt.py): the
    engine cache, and a shape profile for the graphs whose dynamic dimensions are known here: the pillar count P
    (1 to the export's max_pillars), the quadrants Q a slice reads, the cameras J and the image size (the
    lifter's LUT depth K is the LUT's, unknown until it is built: that graph builds from the shapes it sees)."""
    if TENSORRT_PROVIDER not in resolve_providers(config.providers):
        return None
    if entry.precision == "int8":  # static QDQ with uint8 activations: TensorRT takes symmetric int8 only
        raise ProviderError(f"{export_dir}: the {entry.name} int8 graph is made for x86 CPUs (uint8 activations, "
                            "asymmetric); TensorRT runs symmetric int8 only: run fp32 or fp16 graphs there")  # fmt: skip
    img = image
    q_opt = len(quadrants_of_sector(0, num_slices, config.start_deg))
    # the engine is tuned at "opt": a slice's pillar count, far below the cap on a real sweep
    p_opt = max(1, max_pillars // TYPICAL_PILLAR_SHARE)
    dims = {"P": (1, p_opt, max_pillars), "Q": (1, q_opt, NUM_QUADRANTS)}
    if img is not None:
        cams = len(camera_names)
        dims.update(J=(1, cams, cams), H=(img.height,) * 3, W=(img.width,) * 3,
                    Hf=(img.feature_height,) * 3, Wf=(img.feature_width,) * 3)  # fmt: skip
    base = config.tensorrt_cache_dir if config.tensorrt_cache_dir is not None else default_cache_dir()
    # onnxruntime names an engine by the graph's structure and the library versions, not its weights: one folder
    # per graph file's sha256 keeps a retrained export of the same preset off the old one's engines
    cache = Path(base) / entry.sha256[:16]
    try:
        cache.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise ProviderError(f"cannot make the TensorRT engine cache {cache}: {e.strerror or e} "
                            "(DetectorConfig.tensorrt_cache_dir, STREAMDET_TENSORRT_CACHE)") from None  # fmt: skip
    return {TENSORRT_PROVIDER: tensorrt_options(entry.inputs, dims, cache, fp16=entry.precision == "fp16")}


def read_graph(export_dir: Path, manifest: Manifest, name: str, precision: str, verify_sha256: bool) -> tuple[Path, bytes, onnx.ModelProto]:
    """(path, bytes, parsed model) of one of the export's graphs: read once, hashed (``verify_sha256``), no
    external data, the opset and precision its manifest entry records (runtime_ort/graph_files.py)."""
    entry = manifest.graph(name, precision)
    path, raw = read_export_file(export_dir, entry, f"graph file of {name} ({precision})", verify_sha256)
    return path, raw, checked_model(path, raw, entry)


def _open_camera_terms(export_dir: Path, m: Manifest, config: DetectorConfig, grid: GridSpec, img: ImageSpec,
                       lifter: GraphSession, stats: LatencyStats, views: LutViews, lut: Lut) -> CameraTerms | None:  # fmt: skip
    """The per-camera lifts of the image lane (camera_terms.py), checked against the export's fp32 lifter; None
    where they do not apply (``DetectorConfig.camera_terms``)."""
    # small graphs whose row counts change with every camera and quadrant: never TensorRT (an engine per shape)
    terms_providers = without_tensorrt(config.providers)
    fp32 = lifter if config.image_precision == "fp32" and terms_providers == config.providers else None
    read: dict[str, tuple[Path, bytes]] = {}  # the lifters lifter_model read, by precision

    def lifter_model(precision: str) -> onnx.ModelProto:
        path, raw, model = read_graph(export_dir, m, "volumetric_lifter", precision, config.verify_sha256)
        # the fp32 one has no session of its own in an int8 lane: checked here, not taken for a graph that fails to split
        check_graph(m.graph("volumetric_lifter", precision), *model_signature(model), m, grid)
        read[precision] = (path, raw)
        return model

    def fp32_lift(qlut: QuadrantLut, maps: np.ndarray) -> np.ndarray:
        nonlocal fp32
        if fp32 is None:  # the check's reference: the export's fp32 lifter (read and checked by lifter_model first)
            path, raw = read["fp32"] if "fp32" in read else read_graph(export_dir, m, "volumetric_lifter", "fp32", config.verify_sha256)[:2]
            fp32 = GraphSession(path, SessionConfig(terms_providers, config.image_lane_threads), model=raw)
        return fp32.run({"features": maps, **views.lifter_feeds(qlut, maps)})[0]

    session = SessionConfig(terms_providers, config.image_lane_threads, enable_profiling=False)
    form = m.preset.get("lifter", {}).get("form", "volume")  # absent: manifests written before the flat lifter
    return open_camera_terms(
        export_dir, form, lifter_model, config.image_precision, config.camera_terms, int(m.preset["channels"]),
        (img.feature_height, img.feature_width), (grid.quadrant_ny, grid.quadrant_nx), session, stats, fp32_lift,
        views.quadrant_luts(lut, in_use=lut),
    )  # fmt: skip


def executed_gmac(entry: GraphEntry, **sizes: int) -> float:
    """GMAC of one run of ``entry``'s graph: the manifest's count scaled linearly from the sizes it was counted at
    (``gmac_at``) to these (cameras J, image H and W, quadrants Q); sizes it was not counted at stay as counted
    (the slice graph's pillar net at the export's pillar count P, a small share of it)."""
    gmac = entry.gmac
    for name, size in sizes.items():
        at = entry.gmac_at.get(name)
        if at:
            gmac *= size / at
    return gmac


# ---- the LUT a detector runs with (at construction and on every set_calibration) ------------------------------------
def check_lut(lut: Lut, image: ImageSpec, camera_names: tuple[str, ...], grid: GridSpec, export_dir: Path,
              manifest: Manifest) -> Lut:  # fmt: skip
    """``lut`` if it fits the export's cameras, image and feature-map sizes and grid, and is the kind of LUT the
    model was trained and exported with (`export_lut`'s: the manifest's heights per voxel, no minimum depth);
    CalibrationError naming every misfit otherwise. A camera that sees no voxel is logged and warned about
    (BlindCameraWarning), not refused."""
    img = image
    problems = []
    if tuple(lut.camera_names) != camera_names:
        problems.append(f"cameras {list(lut.camera_names)} != the export's {list(camera_names)}")
    if (lut.image_width, lut.image_height) != (img.width, img.height):
        problems.append(f"image size {lut.image_width}x{lut.image_height} != the detector's {img.width}x{img.height}")
    if (lut.feature_width, lut.feature_height, lut.feature_stride) != (img.feature_width, img.feature_height, img.feature_stride):
        problems.append(
            f"feature map {lut.feature_width}x{lut.feature_height}/s{lut.feature_stride} != the export's "
            f"{img.feature_width}x{img.feature_height}/s{img.feature_stride}"
        )
    if lut.grid != grid:
        problems.append(f"grid {lut.grid} != the export's {grid}")
    # Another kind of LUT fits every graph shape but lifts another image BEV than the model learnt from, silently; and
    # pipeline.use_sample_calibration would keep it for its rig, since only calibration_sha256 keys that.
    heights = lut_heights_per_voxel(manifest)
    if lut.heights_per_voxel != heights:
        problems.append(f"heights per voxel {lut.heights_per_voxel} != the export's {heights} "
                        "(manifest preset.lifter.lut_heights_per_voxel)")  # fmt: skip
    if lut.min_depth_m != EXPORT_LUT_MIN_DEPTH_M:
        problems.append(f"min depth {lut.min_depth_m:g} m != the {EXPORT_LUT_MIN_DEPTH_M:g} m every export's LUT is built with")
    if problems:
        raise CalibrationError("the LUT does not fit the graphs: " + "; ".join(problems))
    for name, slots in blind_cameras(lut):
        msg = f"camera {name} sees no voxel of the grid ({slots} LUT slots): its images will not reach the BEV"
        log.warning("%s: %s", export_dir, msg)
        warnings.warn(msg, BlindCameraWarning, stacklevel=_LUT_WARNING_STACKLEVEL)
    return lut


def lut_heights_per_voxel(manifest: Manifest) -> int:
    """The model's LUT heights per voxel (models/presets.py LifterConfig; absent = 1, manifests written before it)."""
    return manifest.preset.get("lifter", {}).get("lut_heights_per_voxel", 1)


def export_lut(rig: Rig, image: ImageSpec, camera_names: tuple[str, ...], grid: GridSpec, manifest: Manifest) -> Lut:
    """The LUT of ``rig`` for this export: its cameras (in order) and image size, grid, feature stride and heights."""
    img = image
    check_rig_fits(rig, camera_names, img.width, img.height)
    return build_lut(rig, grid, img.feature_stride, image_size=(img.width, img.height), min_depth_m=EXPORT_LUT_MIN_DEPTH_M,
                     heights_per_voxel=lut_heights_per_voxel(manifest))  # fmt: skip
