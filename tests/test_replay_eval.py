"""Emission-time matching against hand-made trajectories, and the key-frame interpolation fallback."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from streamdet.data.synth_trajectories import Trajectories
from streamdet.replay.latency_eval import prediction_entries, query_truth, score
from streamdet.replay.record import Recording, SliceRecord
from streamdet.replay.source import Drive, LidarSweep
from streamdet.replay.truth import INTERPOLATED, TRAJECTORIES, GroundTruth, _interpolate
from streamdet.runtime_ort.nms import NmsConfig
from streamdet.runtime_ort.postprocess import Detections

PERIOD_S = 0.05
T0_US = 1_000_000_000
SPEED = 10.0  # m/s along +x
CAR_SIZE = (1.9, 4.6, 1.7)


def car_boxes(t_s: float) -> np.ndarray:
    """(2, 9) world boxes at drive time t: a car moving along x and a parked car."""
    moving = [5.0 + SPEED * t_s, 10.0, 1.0, *CAR_SIZE, 0.0, SPEED, 0.0]
    parked = [-8.0, -12.0, 1.0, *CAR_SIZE, 0.0, 0.0, 0.0]
    return np.array([moving, parked])


def make_drive(sweeps: int = 12) -> Drive:
    out = []
    for i in range(sweeps):
        end = (i + 1) * PERIOD_S
        boxes = car_boxes(end)
        pts = np.concatenate([b[:3] + np.random.default_rng(i).uniform(-0.5, 0.5, (40, 3)) for b in boxes])  # points on both cars
        points = np.zeros((len(pts), 5), np.float32)
        points[:, :3] = pts
        out.append(LidarSweep(i, end, PERIOD_S, points, None, np.eye(4), np.eye(4)))
    return Drive("hand", tuple(out), (), T0_US)


def trajectories(span_s: float = 1.0) -> Trajectories:
    times = np.arange(0.0, span_s, 0.01)
    return Trajectories(
        times_us=(T0_US + times * 1e6).astype(np.int64),
        boxes=np.stack([car_boxes(t) for t in times]),
        names=np.array(["car", "car"]),
        ego2global=np.broadcast_to(np.eye(4), (len(times), 4, 4)).copy(),
    )


def recording(drive: Drive, latency_s: float) -> Recording:
    """A full-sweep mode that detects both cars exactly where they were scanned and emits latency_s later."""
    slices = []
    for sweep in drive.sweeps:
        boxes = car_boxes(sweep.end_s).astype(np.float32)
        dets = Detections(boxes, np.array([0.9, 0.8], np.float32), np.array([0, 0], np.int64))
        slices.append(SliceRecord(sweep.index, 0, 1, sweep.end_s, len(sweep.points), emit_s=sweep.end_s + latency_s,
                                  detections=dets, num_detections=2))  # fmt: skip
    return Recording("full-sweep", drive.name, 1.0, tuple(slices), (), 1.0, 0.0, 0.0)


def scores_at(latency_s: float, first_sweep: int = 1):
    drive = make_drive()
    q = query_truth(drive, GroundTruth(trajectories(), None), first_sweep=first_sweep)
    streaming, offline = prediction_entries(drive, recording(drive, latency_s), q, NmsConfig(), 500)
    return score([q], [streaming]), score([q], [offline])


def test_detections_emitted_at_scan_time_are_perfect():
    streaming, offline = scores_at(0.0)
    assert streaming.map == pytest.approx(1.0) and offline.map == pytest.approx(1.0)


def test_a_late_detection_is_scored_where_the_object_is_when_it_arrives():
    # 0.12 s late: at a query (a rotation's end) the newest emitted sweep was scanned 0.15 s before, so the moving
    # car has gone 1.5 m (matched at the 2 and 4 m thresholds only) and the parked one is where it was. Queries
    # from sweep 3 on, so that every query has an emitted sweep.
    streaming, offline = scores_at(0.12, first_sweep=3)
    assert offline.map == pytest.approx(1.0)
    assert streaming.map_static == pytest.approx(1.0)
    assert streaming.map_moving == pytest.approx(0.5, abs=0.02)
    assert streaming.map < offline.map


def test_queries_before_any_emission_have_no_predictions():
    drive = make_drive()
    q = query_truth(drive, GroundTruth(trajectories(), None))
    streaming, offline = prediction_entries(drive, recording(drive, 0.12), q, NmsConfig(), 500)
    first = q.tokens[0]  # the end of sweep 1: sweep 0 is emitted at 0.17 s
    assert streaming[first] == [] and len(offline[first]) == 2


def test_ground_truth_counts_points_and_knows_its_source():
    drive = make_drive()
    q = query_truth(drive, GroundTruth(trajectories(), None))
    assert q.source == TRAJECTORIES
    for token in q.tokens:
        assert [e["num_pts"] for e in q.entries[token]] == [40, 40]
        assert q.moving[token].tolist() == [True, False]


def test_key_frame_interpolation_is_linear_with_the_interval_velocity():
    a = np.array([0.0, 0, 0, *CAR_SIZE, 0.1, 0, 0])
    b = np.array([5.0, 1, 0, *CAR_SIZE, 0.3, 0, 0])
    track = [(0, a, "car"), (500_000, b, "car")]
    mid = _interpolate(track, 250_000)
    np.testing.assert_allclose(mid[:3], [2.5, 0.5, 0])
    assert mid[6] == pytest.approx(0.2)
    np.testing.assert_allclose(mid[7:9], [10.0, 2.0])
    assert _interpolate(track, 600_000) is None and _interpolate(track, -1) is None


def test_interpolation_takes_the_shorter_arc_of_yaw():
    a = np.array([0.0, 0, 0, *CAR_SIZE, np.pi - 0.1, 0, 0])
    b = np.array([0.0, 0, 0, *CAR_SIZE, -np.pi + 0.1, 0, 0])
    mid = _interpolate([(0, a, "car"), (100, b, "car")], 50)
    assert abs(np.mod(mid[6], 2 * np.pi) - np.pi) < 1e-9


def test_interpolated_ground_truth_matches_the_trajectories_of_a_straight_track():
    key = [0.0, 0.5, 1.0]
    tracks = {"moving": [(int(T0_US + t * 1e6), car_boxes(t)[0] * [1, 1, 1, 1, 1, 1, 1, 0, 0], "car") for t in key],
              "parked": [(int(T0_US + t * 1e6), car_boxes(t)[1], "car") for t in key]}  # fmt: skip
    truth = GroundTruth(None, tracks)
    assert truth.source == INTERPOLATED
    got = truth.at(T0_US + 0.3e6)
    np.testing.assert_allclose(got.boxes, car_boxes(0.3), atol=1e-9)


def test_ground_truth_needs_one_source():
    with pytest.raises(ValueError, match="exactly one"):
        GroundTruth(None, None)


def test_a_late_box_of_a_moving_object_is_no_false_positive_of_the_static_split():
    """0.27 s late, the moving car's box lies 3 m behind it at a query: more than SPLIT_RADIUS_M from the car now,
    but on its trail of the last SPLIT_LAG_S, so it is the moving car's and the static split is untouched."""
    streaming, _ = scores_at(0.27, first_sweep=8)
    assert streaming.map_static == pytest.approx(1.0)
    assert streaming.map_moving < 0.5


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_trail_distance_against_a_sampled_trail(seed):
    from streamdet.replay.latency_eval import trail_distance

    rng = np.random.default_rng(seed)
    points = rng.uniform(-20, 20, (30, 2))
    centres = rng.uniform(-20, 20, (5, 2))
    velocity = rng.uniform(-15, 15, (5, 2))
    velocity[0] = 0.0  # a static object: its trail is its centre
    velocity[1] = np.nan  # an unknown velocity counts as standing still
    got = trail_distance(points, centres, velocity, 0.5)
    taus = np.linspace(0.0, 0.5, 20001)
    for g in range(5):
        trail = centres[g] - np.nan_to_num(velocity[g])[None] * taus[:, None]  # (T, 2) where it was tau ago
        naive = np.linalg.norm(points[:, None, :] - trail[None], axis=-1).min(axis=1)
        np.testing.assert_allclose(got[:, g], naive, atol=1e-3)
    assert trail_distance(np.zeros((0, 2)), centres, velocity, 0.5).shape == (0, 5)


def test_interpolated_truth_scores_no_query_outside_its_key_frames():
    """Key frames at 0.2 s and 0.4 s: queries (rotation ends at 0.1 .. 0.6 s) before the first and after the last
    have no ground truth and are not scored, rather than scored as all false positives."""
    drive = make_drive()
    tracks = {name: [(T0_US + int(t * 1e6), car_boxes(t)[i].copy(), "car") for t in (0.2, 0.4)]
              for i, name in enumerate(("moving", "parked"))}  # fmt: skip
    truth = GroundTruth(None, tracks)
    assert not truth.covers(T0_US + 0.15e6) and truth.covers(T0_US + 0.3e6) and not truth.covers(T0_US + 0.45e6)
    q = query_truth(drive, truth)
    assert q.source == INTERPOLATED
    assert q.sweeps == (3, 4, 5, 6, 7)  # ends 0.20 .. 0.40 s
    streaming, offline = prediction_entries(drive, recording(drive, 0.0), q, NmsConfig(), 500)
    assert score([q], [offline]).map == pytest.approx(1.0)


def test_the_newest_scan_of_a_sector_counts_not_the_last_emitted():
    """Sweep 4's slice finishes after sweep 5's of the same sector: at the query after both, sweep 5's is scored."""
    drive = make_drive()
    q = query_truth(drive, GroundTruth(trajectories(), None))
    rec = recording(drive, 0.0)
    late = {4: 0.34, 5: 0.33, 6: 0.36}  # emit times: sweep 4 after sweep 5, sweep 6 after the query
    slices = tuple(dataclasses.replace(s, emit_s=late[s.sweep]) if s.sweep in late else s for s in rec.slices)
    rec = dataclasses.replace(rec, slices=slices)
    streaming, _ = prediction_entries(drive, rec, q, NmsConfig(), 500)
    token = q.tokens[q.sweeps.index(6)]  # t = 0.35 s: sweeps 4 and 5 emitted, 6 not yet
    moving_x = [e["translation"][0] for e in streaming[token] if e["translation"][1] > 0]
    assert moving_x == pytest.approx([5.0 + SPEED * 0.30])  # sweep 5's scan (end 0.30 s), not sweep 4's


def test_interpolated_truth_carries_each_annotations_attribute():
    """An attribute holds from the key frame that annotates it to the next; the trajectories carry none ("")."""
    moving = [(T0_US + int(t * 1e6), car_boxes(t)[0].copy(), "car", a) for t, a in ((0.2, "vehicle.stopped"), (0.4, "vehicle.moving"))]
    truth = GroundTruth(None, {"m": moving})
    assert truth.at(T0_US + 0.2e6).attribute_names().tolist() == ["vehicle.stopped"]
    assert truth.at(T0_US + 0.3e6).attribute_names().tolist() == ["vehicle.stopped"]
    assert truth.at(T0_US + 0.4e6).attribute_names().tolist() == ["vehicle.moving"]
    q = query_truth(make_drive(), truth)
    assert [e["attribute_name"] for e in q.entries[q.tokens[0]]] == ["vehicle.stopped"]
    q = query_truth(make_drive(), GroundTruth(trajectories(), None))
    assert {e["attribute_name"] for t in q.tokens for e in q.entries[t]} == {""}


def test_synthetic_trajectories_carry_the_annotations_attributes(tiny_synth_data):
    """At every key frame the trajectories sidecar gives each object the attribute its sample_annotation has: the
    replay scores attributes on synthetic data as streamdet-eval does."""
    from streamdet.data.nuscenes import GLOBAL_ANNOTATIONS, NuScenesReader
    from streamdet.data.synth_trajectories import load_trajectories

    reader = NuScenesReader(tiny_synth_data, "v1.0-synth")
    compared = 0
    for token in reader.sample_tokens:
        sample = reader.get(token)
        traj = load_trajectories(tiny_synth_data, reader.scene_name(token))
        assert traj is not None and traj.attributes is not None
        boxes = traj.boxes_at(sample.timestamp_us)
        names = traj.attributes_at(sample.timestamp_us)
        centres = np.asarray(sample.extras[GLOBAL_ANNOTATIONS]["translation"])
        for centre, attribute, label in zip(centres, sample.attribute_names, sample.gt_labels):
            if label < 0:
                continue
            k = int(np.argmin(np.linalg.norm(boxes[:, :3] - centre, axis=1)))
            assert np.linalg.norm(boxes[k, :3] - centre) < 1e-3
            assert names[k] == attribute
            compared += 1
    assert compared > 0


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_attribute_indices_against_the_rule_object_by_object(seed):
    from streamdet.data.synth_tables import ATTRIBUTE_NAMES, attribute_indices
    from streamdet.data.synth_world import Kind

    rng = np.random.default_rng(seed)
    kinds = rng.choice([int(k) for k in Kind], 300)
    speed = rng.choice([0.0, 0.1, 0.25, 0.35, 3.0], 300)
    flag = rng.random(300) < 0.5
    parked = rng.random(300) < 0.5  # placed parked (synth_world.Objects.parked): a kerb or a lot, not a lane or a stop
    got = attribute_indices(kinds, speed, flag, parked)
    for k, v, f, p, a in zip(kinds, speed, flag, parked, got):
        kind = Kind(int(k))
        if kind in (Kind.CAR, Kind.TRUCK, Kind.BUS):
            want = "vehicle.moving" if v > 0.3 else ("vehicle.parked" if p else "vehicle.stopped")
        elif kind in (Kind.BICYCLE, Kind.MOTORCYCLE):
            want = "cycle.with_rider" if f else "cycle.without_rider"
        elif kind == Kind.PEDESTRIAN:
            want = "pedestrian.moving" if v > 0.2 else "pedestrian.standing"
        else:
            want = ""
        assert ATTRIBUTE_NAMES[a] == want
    assert attribute_indices(np.zeros(0, int), 0.0, False, False).shape == (0,)
