"""Execution providers: --providers / STREAMDET_PROVIDERS / DetectorConfig.providers, what a session really started,
and TensorRT's options (shape profiles, engine cache). No GPU here: providers this onnxruntime lacks are faked by
patching onnxruntime's list of available providers, and TensorRT's options are checked as text."""

from __future__ import annotations

import logging
from pathlib import Path

import onnxruntime as ort
import pytest
from click.testing import CliRunner

from streamdet.runtime_ort import sessions
from streamdet.runtime_ort.detector import DetectorConfig, StreamingDetector
from streamdet.runtime_ort.manifest import TensorSpec
from streamdet.runtime_ort.sessions import (
    CPU_PROVIDER,
    PROVIDERS_ENV,
    ProviderError,
    check_started,
    default_providers,
    parse_providers,
    resolve_providers,
)
from streamdet.runtime_ort.tensorrt import CACHE_ENV, default_cache_dir, profile_shapes, tensorrt_options

CUDA, TRT = "CUDAExecutionProvider", "TensorrtExecutionProvider"
GPU_BUILD = [TRT, CUDA, CPU_PROVIDER]


@pytest.fixture
def gpu_build(monkeypatch):
    """onnxruntime as an onnxruntime-gpu build lists its providers (none of them is started here)."""
    monkeypatch.setattr(ort, "get_available_providers", lambda: list(GPU_BUILD))
    monkeypatch.delenv(PROVIDERS_ENV, raising=False)


# ---- parsing -------------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("text", "want"),
    [
        ("cpu", (CPU_PROVIDER,)),
        ("cuda,cpu", (CUDA, CPU_PROVIDER)),
        ("TensorRT, CUDA", (TRT, CUDA)),
        ("trt", (TRT,)),
        ("CUDAExecutionProvider", (CUDA,)),
        ("cudaexecutionprovider", (CUDA,)),  # onnxruntime's names, any case
        ("OpenVINOExecutionProvider,cpu", ("OpenVINOExecutionProvider", CPU_PROVIDER)),
        ("FutureNpuExecutionProvider", ("FutureNpuExecutionProvider",)),  # a provider newer than the list, as written
    ],
)
def test_parse_providers_takes_short_and_onnxruntime_names(text, want):
    assert parse_providers(text) == want


@pytest.mark.parametrize("text", ["auto", "AUTO", "", "  "])
def test_parse_providers_auto_is_the_default_order(text):
    assert parse_providers(text) is None


@pytest.mark.parametrize(("text", "named"), [("gpu", "'gpu'"), ("cuda,,cpu", "''"), ("cpu,auto", "'auto'"), ("cuda;cpu", "'cuda;cpu'"), ("Execution", "'Execution'")])
def test_parse_providers_refuses_an_unknown_name_naming_it(text, named):
    with pytest.raises(ValueError, match=rf"--providers: unknown execution provider {named}.*cpu, cuda, tensorrt"):
        parse_providers(text)


@pytest.mark.parametrize("text", ["cuda,CUDAExecutionProvider", "trt,tensorrt", "cpu,cpu"])
def test_parse_providers_refuses_a_provider_named_twice(text):
    with pytest.raises(ValueError, match="twice"):
        parse_providers(text)


def test_default_providers_read_the_environment():
    assert default_providers({}) is None
    assert default_providers({PROVIDERS_ENV: "auto"}) is None
    assert default_providers({PROVIDERS_ENV: " "}) is None
    assert default_providers({PROVIDERS_ENV: "cuda"}) == (CUDA,)
    with pytest.raises(ValueError, match=f"environment variable {PROVIDERS_ENV}: unknown execution provider 'gpu'"):
        default_providers({PROVIDERS_ENV: "gpu"})


# ---- resolving ------------------------------------------------------------------------------------------------


def test_the_default_order_is_cuda_then_cpu_never_tensorrt(gpu_build):
    assert resolve_providers(None) == [CUDA, CPU_PROVIDER]  # TensorRT builds engines for minutes: only when asked


def test_the_default_order_on_a_cpu_build(monkeypatch):
    monkeypatch.setattr(ort, "get_available_providers", lambda: ["AzureExecutionProvider", CPU_PROVIDER])
    monkeypatch.delenv(PROVIDERS_ENV, raising=False)
    assert resolve_providers(None) == [CPU_PROVIDER]


def test_asked_providers_come_in_order_with_the_cpu_appended(gpu_build):
    assert resolve_providers((TRT, CUDA)) == [TRT, CUDA, CPU_PROVIDER]
    assert resolve_providers((CPU_PROVIDER,)) == [CPU_PROVIDER]


def test_tensorrt_asked_alone_gets_cuda_behind_it(gpu_build, monkeypatch):
    assert resolve_providers((TRT,)) == [TRT, CUDA, CPU_PROVIDER]  # the nodes TensorRT rejects run on CUDA
    assert resolve_providers((TRT, CPU_PROVIDER)) == [TRT, CUDA, CPU_PROVIDER]
    monkeypatch.setattr(ort, "get_available_providers", lambda: [TRT, CPU_PROVIDER])
    assert resolve_providers((TRT,)) == [TRT, CPU_PROVIDER]  # a build without CUDA


def test_the_camera_terms_never_run_on_tensorrt(gpu_build, monkeypatch):
    from streamdet.runtime_ort.sessions import without_tensorrt

    assert without_tensorrt(None) is None
    assert without_tensorrt((TRT, CUDA)) == (CUDA,)
    assert without_tensorrt((TRT,)) == (CUDA,)
    assert without_tensorrt((CUDA, CPU_PROVIDER)) == (CUDA, CPU_PROVIDER)
    monkeypatch.setenv(PROVIDERS_ENV, "tensorrt")
    assert without_tensorrt(None) == (CUDA,)
    monkeypatch.setattr(ort, "get_available_providers", lambda: [TRT, CPU_PROVIDER])
    assert without_tensorrt((TRT,)) == (CPU_PROVIDER,)


def test_sessions_raise_a_provider_failure_in_run_instead_of_moving_to_the_cpu(tiny_export):
    graph = sessions.GraphSession(tiny_export / "slice_head.onnx", sessions.SessionConfig(providers=("cpu",)))
    assert graph.session._enable_fallback is False  # onnxruntime's Python fallback off: EPFail becomes GraphRunError
    assert sessions.ort_session(tiny_export / "slice_head.onnx")._enable_fallback is False


def test_a_graph_an_accelerator_cannot_load_is_a_provider_error_not_a_broken_file(tiny_export, monkeypatch):
    monkeypatch.setattr(sessions, "resolve_providers", lambda requested: [CUDA, CPU_PROVIDER])

    def failing(src, sess_options=None, providers=None, **kw):
        raise ort.capi.onnxruntime_pybind11_state.Fail("TensorRT EP could not build the engine")

    monkeypatch.setattr(ort, "InferenceSession", failing)
    with pytest.raises(ProviderError, match=r"cannot create a session of this graph on \['CUDAExecutionProvider'.*--providers cpu"):
        sessions.GraphSession(tiny_export / "slice_head.onnx", sessions.SessionConfig(providers=(CUDA,)))


def test_the_environment_chooses_where_the_caller_names_none(gpu_build, monkeypatch):
    monkeypatch.setenv(PROVIDERS_ENV, "cpu")
    assert resolve_providers(None) == [CPU_PROVIDER]
    assert resolve_providers((CUDA,)) == [CUDA, CPU_PROVIDER]  # the caller's choice wins


def test_a_provider_this_build_lacks_is_an_error_naming_the_gpu_wheel(monkeypatch):
    monkeypatch.delenv(PROVIDERS_ENV, raising=False)
    if CUDA in ort.get_available_providers():
        pytest.skip("this onnxruntime has CUDA")
    with pytest.raises(ProviderError, match=r"\['CUDAExecutionProvider'\] are not available.*onnxruntime-gpu"):
        resolve_providers((CUDA,))
    assert issubclass(ProviderError, ValueError)  # the tools' input errors


def test_a_provider_named_explicitly_that_did_not_start_raises():
    with pytest.raises(ProviderError, match=r"slice_head.onnx: onnxruntime could not start \['CUDAExecutionProvider'\].*--providers"):
        check_started("exp/slice_head.onnx", [CUDA, CPU_PROVIDER], [CPU_PROVIDER], explicit=True)


def test_the_default_order_falling_back_to_the_cpu_is_logged(caplog):
    with caplog.at_level(logging.WARNING, logger=sessions.__name__):
        check_started("slice_head.onnx", [CUDA, CPU_PROVIDER], [CPU_PROVIDER], explicit=False)
    assert "could not start ['CUDAExecutionProvider']" in caplog.text
    check_started("slice_head.onnx", [CUDA, CPU_PROVIDER], [CUDA, CPU_PROVIDER], explicit=True)  # started: nothing


def test_a_session_that_loses_an_asked_provider_raises(tiny_export, monkeypatch):
    """onnxruntime-gpu without its CUDA libraries: the session starts on the CPU alone (faked: CUDA dropped)."""
    monkeypatch.setattr(sessions, "resolve_providers", lambda requested: [CUDA, CPU_PROVIDER])
    real = ort.InferenceSession

    def cpu_only(src, sess_options=None, providers=None, **kw):
        return real(src, sess_options=sess_options, providers=[p for p in providers if p == CPU_PROVIDER])

    monkeypatch.setattr(ort, "InferenceSession", cpu_only)
    with pytest.raises(ProviderError, match="could not start"):
        sessions.GraphSession(tiny_export / "slice_head.onnx", sessions.SessionConfig(providers=(CUDA,)))


# ---- DetectorConfig and the detector ---------------------------------------------------------------------------


def test_detector_config_takes_short_names_and_refuses_unknown_ones():
    assert DetectorConfig(providers=("cuda", "cpu")).providers == (CUDA, CPU_PROVIDER)
    assert DetectorConfig().providers is None
    with pytest.raises(ValueError, match="DetectorConfig.providers: unknown execution provider 'gpu'"):
        DetectorConfig(providers=("gpu",))
    with pytest.raises(ValueError, match="tuple of provider names"):
        DetectorConfig(providers="cuda")
    with pytest.raises(ValueError, match="tensorrt_cache_dir"):
        DetectorConfig(tensorrt_cache_dir=3)


def test_the_detector_runs_on_the_providers_asked(tiny_export):
    det = StreamingDetector(tiny_export, DetectorConfig(providers=("cpu",)))
    assert det.providers == (CPU_PROVIDER,)
    assert det._provider_options(det.manifest.graph("slice_head", "fp32")) is None  # no TensorRT: no options
    det.close()


def test_tensorrt_refuses_the_int8_graphs(tiny_int8_export, tmp_path, gpu_build):
    det = StreamingDetector(tiny_int8_export.path, DetectorConfig(providers=("cpu",)))
    det.config = DetectorConfig(providers=("tensorrt",), tensorrt_cache_dir=tmp_path)
    with pytest.raises(ProviderError, match="slice_head int8 graph is made for x86 CPUs.*fp32 or fp16"):
        det._provider_options(det.manifest.graph("slice_head", "int8"))
    det.close()


def test_the_detector_gives_tensorrt_a_profile_of_the_pillar_count(tiny_export, tmp_path, gpu_build):
    det = StreamingDetector(tiny_export, DetectorConfig(providers=("cpu",)))
    det.config = DetectorConfig(providers=("tensorrt", "cuda"), tensorrt_cache_dir=tmp_path / "engines")
    max_pillars = int(det.manifest.preset["pillars"]["max_pillars"])
    points = int(det.manifest.preset["pillars"]["max_points_per_pillar"])
    slice_opts = det._provider_options(det.manifest.graph("slice_head", "fp32"))[TRT]
    assert slice_opts["trt_engine_cache_enable"] == "True"
    # one folder per graph file: onnxruntime names engines by structure, not weights
    sha = det.manifest.graph("slice_head", "fp32").sha256
    assert slice_opts["trt_engine_cache_path"] == str(tmp_path / "engines" / sha[:16])
    assert (tmp_path / "engines" / sha[:16]).is_dir()
    assert f"pillar_features:{max_pillars // 8}x{points}x11" in slice_opts["trt_profile_opt_shapes"]
    assert f"pillar_features:1x{points}x11" in slice_opts["trt_profile_min_shapes"]
    assert f"pillar_features:{max_pillars}x{points}x11" in slice_opts["trt_profile_max_shapes"]
    assert f"pillar_index:{max_pillars}" in slice_opts["trt_profile_max_shapes"]
    assert "image_bev:1x" in slice_opts["trt_profile_opt_shapes"]  # 8 slices: one quadrant a slice
    assert "image_bev:4x" in slice_opts["trt_profile_max_shapes"]
    assert "trt_fp16_enable" not in slice_opts
    assert det._provider_options(det.manifest.graph("slice_head", "fp16"))[TRT]["trt_fp16_enable"] == "True"
    img = det.image
    encoder = det._provider_options(det.manifest.graph("image_encoder", "fp32"))[TRT]
    cams = len(det.camera_names)
    assert encoder["trt_profile_max_shapes"] == f"images:{cams}x{img.height}x{img.width}x3"
    # the lifter's LUT depth K is the LUT's: no explicit profile, only the cache
    lifter = det._provider_options(det.manifest.graph("volumetric_lifter", "fp32"))[TRT]
    assert "trt_profile_min_shapes" not in lifter and lifter["trt_engine_cache_enable"] == "True"
    det.close()


# ---- TensorRT's options as text -------------------------------------------------------------------------------


def _spec(name, *shape):
    return TensorSpec(name, tuple(shape), "float32")


def test_profile_shapes_writes_every_dynamic_input():
    inputs = (_spec("x", "P", 16, 11), _spec("fixed", 3, 4), _spec("bev", "Q", 32, 8, 8))
    got = profile_shapes(inputs, {"P": (1, 100, 200), "Q": (1, 1, 4)})
    assert got == {
        "trt_profile_min_shapes": "x:1x16x11,bev:1x32x8x8",
        "trt_profile_opt_shapes": "x:100x16x11,bev:1x32x8x8",
        "trt_profile_max_shapes": "x:200x16x11,bev:4x32x8x8",
    }


def test_profile_shapes_is_none_for_a_static_graph_or_an_unknown_dimension():
    assert profile_shapes((_spec("a", 1, 2),), {"P": (1, 2, 3)}) is None
    assert profile_shapes((_spec("a", "P"), _spec("b", "K", 4)), {"P": (1, 2, 3)}) is None
    assert profile_shapes((), {}) is None


@pytest.mark.parametrize("bad", [(0, 1, 2), (3, 2, 4), (1, 2), (1.0, 2, 3), (True, 2, 3)])
def test_tensorrt_options_refuse_a_bad_range(bad, tmp_path):
    with pytest.raises(ValueError, match="'P'"):
        tensorrt_options((_spec("a", "P"),), {"P": bad}, tmp_path)


def test_default_cache_dir_order(tmp_path):
    assert default_cache_dir({CACHE_ENV: str(tmp_path)}) == tmp_path
    assert default_cache_dir({"XDG_CACHE_HOME": "/c"}) == Path("/c/streamdet/tensorrt")
    assert default_cache_dir({}) == Path.home() / ".cache" / "streamdet" / "tensorrt"


# ---- the tools ------------------------------------------------------------------------------------------------


def test_streamdet_run_refuses_an_unknown_provider(tiny_export, tmp_path):
    from streamdet.evaluation.run_cli import main

    result = CliRunner().invoke(main, ["--export-dir", str(tiny_export), "--out", str(tmp_path / "o"), "--providers", "gpu"])
    assert result.exit_code == 2
    assert "unknown execution provider 'gpu'" in result.output and "--providers" in result.output


def test_streamdet_run_refuses_a_provider_this_build_lacks(tiny_export, tmp_path, monkeypatch):
    if CUDA in ort.get_available_providers():
        pytest.skip("this onnxruntime has CUDA")
    from streamdet.evaluation.run_cli import main

    result = CliRunner().invoke(main, ["--export-dir", str(tiny_export), "--out", str(tmp_path / "o"), "--providers", "cuda"])
    assert result.exit_code == 1
    assert "not available in this onnxruntime build" in result.output
    assert not (tmp_path / "o").exists()


def test_streamdet_run_reports_the_providers_it_ran_on(tiny_export, tmp_path):
    from streamdet.evaluation.run_cli import main

    result = CliRunner().invoke(main, ["--export-dir", str(tiny_export), "--out", str(tmp_path / "o"), "--providers", "cpu"])
    assert result.exit_code == 0, result.output
    assert "CPUExecutionProvider" in result.output.splitlines()[0]


def test_eval_refuses_providers_in_the_files_mode(tmp_path):
    from streamdet.evaluation.cli import main

    gt = tmp_path / "gt.json"
    gt.write_text('{"results": {}}')
    result = CliRunner().invoke(main, ["--gt", str(gt), "--results", str(gt), "--providers", "cpu"])
    assert result.exit_code == 2
    assert "--providers (dataset mode) not read in the files mode" in result.output


def test_every_tool_that_runs_graphs_takes_providers():
    from streamdet.bag.cli import run_cmd
    from streamdet.evaluation.cli import main as eval_main
    from streamdet.evaluation.run_cli import main as run_main
    from streamdet.replay.cli import main as replay_main
    from streamdet.studies.cli import main as study_main

    for command in (run_cmd, eval_main, run_main, replay_main, *study_main.commands.values()):
        assert "providers" in {p.name for p in command.params}, command.name


def test_replay_config_records_the_providers(tmp_path):
    from streamdet.replay.run import ReplayConfig

    assert ReplayConfig(tmp_path, tmp_path, providers=(CPU_PROVIDER,)).to_dict()["providers"] == [CPU_PROVIDER]
    assert ReplayConfig(tmp_path, tmp_path).to_dict()["providers"] is None


# ---- threads per session (portability audit L6) -----------------------------------------------------------------


@pytest.mark.parametrize(
    ("image", "slices", "cpus", "want"),
    [(1, 1, 2, None), (1, 1, 1, None), (2, 1, 2, "2 + 1"), (1, 1, 64, None), (32, 32, 64, None), (64, 64, 64, "64 + 64"),
     (0, 1, 8, "8 + 1"), (0, 0, 1, None)],
)
def test_lanes_oversubscribe(image, slices, cpus, want):
    from streamdet.runtime_ort.lanes import lanes_oversubscribe

    assert lanes_oversubscribe(image, slices, cpus) == want


def test_a_runner_warns_when_its_lanes_threads_exceed_the_cpus(tiny_export, monkeypatch):
    import warnings

    from streamdet.runtime_ort import lanes

    monkeypatch.setattr(lanes, "usable_cpus", lambda: 2)
    with StreamingDetector(tiny_export, DetectorConfig(image_lane_threads=2, slice_lane_threads=2)) as det:
        with pytest.warns(RuntimeWarning, match=r"2 \+ 2 on 2 usable CPU\(s\).*per session"):
            lanes.StreamingRunner(det).close()
    with StreamingDetector(tiny_export) as det, warnings.catch_warnings():
        warnings.simplefilter("error")
        lanes.StreamingRunner(det).close()  # 1 + 1 on 2 CPUs: quiet


def test_a_replay_records_the_providers_asked_and_used(tiny_drive_data, tiny_export, tmp_path):
    import json

    from streamdet.replay import cli as replay_cli

    out = tmp_path / "r.json"
    args = ["--data", str(tiny_drive_data), "--split", "all", "--export-dir", str(tiny_export), "--max-seconds", "0.1",
            "--mode", "sequential", "--time-scale", "2", "--providers", "cpu", "--json", str(out)]  # fmt: skip
    result = CliRunner().invoke(replay_cli.main, args)
    assert result.exit_code == 0, result.output
    assert "onnxruntime CPUExecutionProvider; " in result.output
    config = json.loads(out.read_text())["config"]
    assert config["providers"] == [CPU_PROVIDER] and config["providers_used"] == [CPU_PROVIDER]


def test_streamdet_run_names_the_cpu(tiny_export, tmp_path):
    from streamdet.evaluation.run_cli import main

    result = CliRunner().invoke(main, ["--export-dir", str(tiny_export), "--out", str(tmp_path / "o")])
    assert result.exit_code == 0, result.output
    assert result.output.splitlines()[1].startswith("CPU: ") and "threads usable" in result.output


def test_bench_header_says_when_the_flags_are_unknown():
    from streamdet.benchmarks import report
    from streamdet.benchmarks.probe import ProbeResult

    machine = {"cpu_model": "x", "cpu_flags": [], "cpu_flags_source": None, "logical_cpus": 2, "load_average_1_5_15": [0, 0, 0],
               "onnxruntime": "1", "torch": "2"}  # fmt: skip
    meta = {"date": "d", "preset": "p", "machine": machine, "threads": 2, "repeat": 1, "warmup": 1, "budget_s": 1.0}
    header = report.format_header(meta, ProbeResult((1.0,), 8, 2))
    assert "(SIMD flags unknown)" in header
    machine.update(cpu_flags=["avx2"], cpu_flags_source="numpy")
    assert "(avx2: numpy's CPU features)" in report.format_header(meta, ProbeResult((1.0,), 8, 2))
