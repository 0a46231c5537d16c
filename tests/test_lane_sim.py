"""benchmarks/lane_sim.py: the phase-locked lane on a clock moved by stage costs, scored as the replay scores."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from click.testing import CliRunner

from streamdet.benchmarks.lane_sim import LaneCosts, SimConfig, costs_from_replay, main, simulate

# the bundled rig's quadrants (tests/test_runtime_phase_lock.py: SEES; the CLI reads them from an export's LUT)
CAMERAS = {0: ("CAM_FRONT", "CAM_FRONT_RIGHT", "CAM_BACK_RIGHT"), 1: ("CAM_FRONT", "CAM_FRONT_LEFT", "CAM_BACK_LEFT"),
           2: ("CAM_BACK", "CAM_BACK_LEFT"), 3: ("CAM_BACK", "CAM_BACK_RIGHT")}  # fmt: skip
SHORT = SimConfig(seconds=3.0)


def test_a_lane_without_costs_fuses_at_least_the_newest_frames_in_every_slice():
    r = simulate(LaneCosts(0.0, 0.0, 0.0), CAMERAS, SHORT)
    assert r.staleness_ms.size > 0.9 * (3.0 - 0.5) * 20 * 8  # every slice after the warm-up but the first few
    assert (r.staleness_ms <= 1e-9).all()  # never older than the newest frames by the scan start
    assert (r.staleness_ms < 0).any()  # and frames that came during the scan made it in (as a replay can show)
    assert r.busy_cores == 0.0 and r.stats.quadrant_lifts > 0


@pytest.mark.parametrize("seed", [0, 1])
def test_costlier_stages_leave_staler_images_and_a_busier_lane(seed):
    cheap = simulate(LaneCosts(1.0, 0.4, 1.0, jitter=0.1), CAMERAS, SimConfig(seconds=3.0, seed=seed))
    dear = simulate(LaneCosts(6.0, 2.5, 6.0, jitter=0.1), CAMERAS, SimConfig(seconds=3.0, seed=seed))
    assert np.percentile(dear.staleness_ms, 95) > np.percentile(cheap.staleness_ms, 95)
    assert dear.busy_cores > cheap.busy_cores > 0
    assert (dear.staleness_ms > 25).mean() > (cheap.staleness_ms > 25).mean()
    # the stale slices of a lane short of time gather after the rotations that brought every camera's frame
    by = dear.by_recent_frames()
    most = max(by)
    assert most == 6 and by[most][0] / by[most][1] > (dear.staleness_ms > 25).mean()
    assert sum(total for _, total in by.values()) == dear.staleness_ms.size


def test_the_busy_share_is_the_work_of_every_frame_and_lift():
    costs = LaneCosts(2.0, 1.0, 3.0)
    r = simulate(costs, CAMERAS, SHORT)
    s = r.stats
    work_s = (s.cameras_encoded * (costs.encode_ms + costs.term_ms) + (s.quadrant_lifts + 4 * s.full_updates) * costs.tail_ms) * 1e-3
    assert r.busy_cores == pytest.approx(work_s / SHORT.seconds)


def test_a_slice_that_reads_later_reads_fresher_images():
    costs = LaneCosts(4.4, 1.8, 4.2)
    now = simulate(costs, CAMERAS, SHORT)
    later = simulate(costs, CAMERAS, SimConfig(seconds=3.0, read_delay_ms=20.0))
    assert later.staleness_ms.mean() < now.staleness_ms.mean()


@pytest.mark.parametrize("field, bad", [("encode_ms", -1.0), ("term_ms", math.nan), ("tail_ms", math.inf), ("jitter", True), ("encode_ms", "4")])
def test_bad_costs_are_refused(field, bad):
    values = {"encode_ms": 1.0, "term_ms": 1.0, "tail_ms": 1.0, field: bad}
    with pytest.raises(ValueError, match=f"LaneCosts.{field}"):
        LaneCosts(**values)
    with pytest.raises(ValueError, match="cost scale"):
        LaneCosts(1.0, 1.0, 1.0).scaled(0.0)


@pytest.mark.parametrize("field, bad", [("lidar_hz", 0.0), ("seconds", -1.0), ("read_delay_ms", math.nan), ("warm_up_s", 20.0)])
def test_bad_configs_are_refused(field, bad):
    with pytest.raises(ValueError, match=f"SimConfig.{field}"):
        SimConfig(**{field: bad})


def test_quadrants_without_cameras_or_cameras_without_axes_are_refused():
    with pytest.raises(ValueError, match=r"quadrant\(s\) \[2\]"):
        simulate(LaneCosts(1, 1, 1), {**CAMERAS, 2: ()}, SHORT)
    with pytest.raises(ValueError, match="CAM_EXTRA"):
        simulate(LaneCosts(1, 1, 1), {**CAMERAS, 3: ("CAM_EXTRA",)}, SHORT)


def _replay_json(tmp_path, stages: dict, frames: tuple[int, ...] | None) -> None:
    recordings = [{"phase_lock": None if frames is None else {"cameras_encoded": f}} for f in frames or (0,)]
    doc = {"modes": {"streaming": {"stages": stages, "recordings": recordings}}}
    (tmp_path / "replay.json").write_text(json.dumps(doc))


def test_a_replays_costs_are_per_frame_encoded_and_per_tail(tmp_path):
    stages = {"image_encoder": {"runs": 300, "mean_ms": 8.0}, "lifter_partial": {"runs": 500, "mean_ms": 2.0},
              "lifter_tail": {"runs": 250, "mean_ms": 5.0}, "slice_head": {"runs": 800, "mean_ms": 4.0}}  # fmt: skip
    _replay_json(tmp_path, stages, (150, 250))
    costs = costs_from_replay(tmp_path, jitter=0.2)
    assert (costs.encode_ms, costs.term_ms, costs.tail_ms, costs.jitter) == (6.0, 2.5, 5.0, 0.2)
    assert costs_from_replay(tmp_path / "replay.json", jitter=0.2) == costs
    _replay_json(tmp_path, stages, None)  # a `full` replay: no phase-locked lane, no frames counted
    with pytest.raises(ValueError, match="no frames encoded"):
        costs_from_replay(tmp_path)
    _replay_json(tmp_path, {"slice_head": stages["slice_head"]}, (10,))
    with pytest.raises(ValueError, match="image_encoder"):
        costs_from_replay(tmp_path)


def test_the_cli_prints_a_row_per_cost_scale_and_writes_json(tiny_export, tmp_path):
    out = tmp_path / "sim.json"
    args = ["--export-dir", str(tiny_export), "--encode-ms", "4", "--term-ms", "1.5", "--tail-ms", "4", "--seconds", "2",
            "--cost-scale", "1", "--cost-scale", "0.5", "--json", str(out)]  # fmt: skip
    result = CliRunner().invoke(main, args)
    assert result.exit_code == 0, result.output
    assert "camera axes from the export's calibration: CAM_FRONT 90.2 deg" in result.output  # the bundled sample's rig
    rows = [line for line in result.output.splitlines() if line.startswith("| 1 |") or line.startswith("| 0.5 |")]
    assert len(rows) == 2
    doc = json.loads(out.read_text())
    assert [r["cost_scale"] for r in doc["rows"]] == [1.0, 0.5] and doc["costs"]["encode_ms"] == 4.0
    assert set(doc["rows"][0]["staleness_added_ms"]) == {"p50", "p95", "p99"}
    missing = CliRunner().invoke(main, ["--export-dir", str(tiny_export), "--encode-ms", "4"])
    assert missing.exit_code != 0 and "no cost for term_ms, tail_ms" in missing.output


def test_the_cli_says_which_replay_gave_no_costs(tiny_export, tmp_path):
    (tmp_path / "replay.json").write_text("{not json")
    bad = CliRunner().invoke(main, ["--export-dir", str(tiny_export), "--costs-from", str(tmp_path)])
    assert bad.exit_code != 0 and f"--costs-from {tmp_path}" in bad.output
    (tmp_path / "replay.json").write_text(json.dumps({"modes": {}}))
    bad = CliRunner().invoke(main, ["--export-dir", str(tiny_export), "--costs-from", str(tmp_path)])
    assert bad.exit_code != 0 and "KeyError" in bad.output


def test_the_exports_layout_is_its_luts_cameras_and_its_rigs_axes(tiny_export, tmp_path):
    import shutil

    from streamdet.benchmarks.lane_sim import export_layout
    from streamdet.replay.cost import AXES_DEG

    cameras, axes = export_layout(tiny_export)
    assert set(cameras) == {0, 1, 2, 3} and all(cameras.values())
    assert axes == pytest.approx(AXES_DEG, abs=0.06)  # AXES_DEG: the bundled rig's, to 0.1 deg
    # an export whose calibration lies elsewhere: its LUT still says the cameras, the axes are not read
    moved = tmp_path / "export"
    shutil.copytree(tiny_export, moved)
    manifest = json.loads((moved / "manifest.json").read_text())
    manifest["lut"]["calibration_source"] = "/nowhere/calibration.json"
    (moved / "manifest.json").write_text(json.dumps(manifest))
    cameras2, axes2 = export_layout(moved)
    assert cameras2 == cameras and axes2 is None


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_faster_part_never_fuses_a_rotation_older_images(seed):
    """At 0.9x the Xeon guest's stage costs (docs/replay.md, "Ready lifts") a camera's frame that came just before a
    pass made its encode-and-lift miss it, and the pass was skipped: its slice read a lift two camera periods old
    (p99 100 ms, where 1.0x gave 10 ms). The lane now lifts such a pass from the frames ready (that camera's previous
    one): no slice is older than a frame of the newest by more than the step of one camera's frame."""
    costs = LaneCosts(2.01, 1.54, 3.47, jitter=0.15).scaled(0.9)
    r = simulate(costs, CAMERAS, SimConfig(seconds=10.0, seed=seed))
    assert r.stats.ready_lifts > 0
    assert np.percentile(r.staleness_ms, 99) <= 25
    assert (r.staleness_ms > 25).mean() < 0.01


def test_a_busy_lane_makes_no_ready_lifts():
    """Past READY_BUSY_SHARE of the rotation spent working, a ready lift would push later lifts back: none is made."""
    r = simulate(LaneCosts(2.01, 1.54, 3.47).scaled(2.0), CAMERAS, SimConfig(seconds=5.0))
    assert r.busy_cores > 0.8 and r.stats.ready_lifts == 0
