"""The nuScenes attributes of the synthetic world: ``vehicle.parked`` only where the layout parked a vehicle (kerb,
bay, lot); a vehicle waiting in a lane of either street or at a bus stop is ``vehicle.stopped``. The vectorised rule
(``synth_tables.attribute_indices``), the layout's parked flags and a written dataset's tables, each against a naive
per-object reference."""

from __future__ import annotations

import json

import numpy as np
import pytest

from streamdet.data.synth_road import CROSS_HALF_WIDTH_M, PARKING_OFFSET_M, ROAD_HALF_WIDTH_M
from streamdet.data.synth_tables import ATTRIBUTE_NAMES, attribute_indices, attribute_of, token
from streamdet.data.synth_trajectories import load_trajectories
from streamdet.data.synth_world import Kind, WorldConfig, make_scene
from streamdet.data.synth_writer import SynthConfig, generate_dataset

VEHICLES = (Kind.CAR, Kind.TRUCK, Kind.BUS)
CYCLES = (Kind.BICYCLE, Kind.MOTORCYCLE)
# Seed 0's scene 0 (one key frame) holds, within the annotation range, vehicles waiting on the cross street, buses
# at stops and parked cars: every case the attribute has to tell apart.
CONFIG = SynthConfig(num_scenes=1, seed=0, resolution=(160, 90), world=WorldConfig(samples_per_scene=1))


def _naive_attribute(kind: int, speed: float, flag: bool, parked: bool) -> str:
    kind = Kind(int(kind))
    if kind in VEHICLES:
        if speed > 0.3:
            return "vehicle.moving"
        return "vehicle.parked" if parked else "vehicle.stopped"
    if kind in CYCLES:
        return "cycle.with_rider" if flag else "cycle.without_rider"
    if kind == Kind.PEDESTRIAN:
        return "pedestrian.moving" if speed > 0.2 else "pedestrian.standing"
    return ""


def _place(scene, k: int, t_s: float) -> str:
    """Where stationary object k stands, from geometry alone (the reference the parked flag must agree with): in the
    cross street's strip (which has no parking), at a bus stop, in a main-road lane, or beside the road (kerb, bay,
    lot: beyond the old rule's distance, which holds on the main road)."""
    objs = scene.objects
    s, d = (float(v) for v in scene.to_road(objs.boxes_at(t_s)[k, :2]))
    if scene.cross_s_m is not None and abs(s - scene.cross_s_m) < CROSS_HALF_WIDTH_M and abs(d) > ROAD_HALF_WIDTH_M:
        return "cross-street lane"
    if objs.kind[k] == Kind.BUS:  # buses never park in this world: off the lanes, a bus waits at a stop
        return "bus stop" if abs(d) > PARKING_OFFSET_M - 1.0 else "main-road lane"
    return "beside the road" if abs(d) > PARKING_OFFSET_M - 1.0 else "main-road lane"


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_attribute_indices_match_a_per_object_reference(seed):
    rng = np.random.default_rng(seed)
    n = 400
    kinds = rng.choice([int(k) for k in Kind], n)
    speed = rng.choice([0.0, 0.1, 0.2, 0.25, 0.3, 0.35, 3.0], n)
    flag = rng.random(n) < 0.5
    parked = rng.random(n) < 0.5
    got = attribute_indices(kinds, speed, flag, parked)
    assert got.dtype == np.uint8 and got.shape == (n,)
    for k, v, f, p, a in zip(kinds, speed, flag, parked, got):
        want = _naive_attribute(k, v, f, p)
        assert ATTRIBUTE_NAMES[a] == want, (Kind(int(k)), v, f, p)
        assert attribute_of(int(k), float(v), bool(f), bool(p)) == want
    # broadcast: one flag against (T, K) codes, as the trajectories sidecar asks
    assert attribute_indices(kinds[None, :3], speed[:3], flag[:3], np.zeros((2, 1), bool)).shape == (2, 3)
    assert attribute_indices(np.zeros(0, int), 0.0, False, False).shape == (0,)


def test_attribute_indices_refuse_a_distance_for_the_parked_flag():
    # The rule used to take the distance to the main road; a distance passed now would read as "parked".
    with pytest.raises(TypeError, match="parked must be booleans.*float64"):
        attribute_indices([int(Kind.CAR)], [0.0], [False], [7.0])


@pytest.mark.parametrize("seed", range(6))
def test_the_layout_parks_what_stands_beside_the_road(seed):
    scene = make_scene(seed, 0, WorldConfig())
    objs = scene.objects
    speed = np.linalg.norm(objs.velocity, axis=1)
    assert objs.parked.dtype == bool and objs.parked.shape == (len(objs),)
    assert not np.any(objs.parked & (speed > 0)), "a parked object moves"
    assert set(objs.kind[objs.parked].tolist()) <= {int(k) for k in (Kind.CAR, Kind.TRUCK, *CYCLES)}
    assert not np.any(objs.parked & np.isin(objs.kind, [int(k) for k in CYCLES]) & objs.flag), "a parked cycle has a rider"
    t = float(scene.sample_times_s[0])
    for k in np.flatnonzero(np.isin(objs.kind, [int(v) for v in VEHICLES]) & (speed == 0)):
        place = _place(scene, int(k), t)
        assert bool(objs.parked[k]) == (place == "beside the road"), (Kind(int(objs.kind[k])), place)


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    root = tmp_path_factory.mktemp("synth_attributes")
    generate_dataset(root, CONFIG)
    return root


def test_cross_street_waits_and_bus_stops_are_stopped_in_the_tables(dataset):
    tables = {name: json.loads((dataset / CONFIG.version / f"{name}.json").read_text())
              for name in ("sample_annotation", "attribute", "sample")}  # fmt: skip
    attribute_name = {a["token"]: a["name"] for a in tables["attribute"]}
    scene = make_scene(CONFIG.seed, 0, CONFIG.world)
    objs = scene.objects
    t = float(scene.sample_times_s[0])
    index_of = {token("streamdet-synth", CONFIG.seed, "instance", scene.name, k): k for k in range(len(objs))}
    speed = np.linalg.norm(objs.velocity, axis=1)
    seen: dict[tuple[str, str], int] = {}
    for ann in tables["sample_annotation"]:
        k = index_of[ann["instance_token"]]
        names = [attribute_name[a] for a in ann["attribute_tokens"]]
        want = _naive_attribute(objs.kind[k], speed[k], bool(objs.flag[k]), bool(objs.parked[k]))
        assert names == ([want] if want else []), (Kind(int(objs.kind[k])), k)
        if objs.kind[k] in [int(v) for v in VEHICLES] and speed[k] == 0:
            place = _place(scene, k, t)
            assert names == ["vehicle.parked" if place == "beside the road" else "vehicle.stopped"], (k, place)
            seen[place, names[0]] = seen.get((place, names[0]), 0) + 1
    assert seen.get(("cross-street lane", "vehicle.stopped"), 0) >= 1, seen
    assert seen.get(("bus stop", "vehicle.stopped"), 0) >= 1, seen
    assert seen.get(("beside the road", "vehicle.parked"), 0) >= 1, seen
    assert not any(name == "vehicle.parked" and place != "beside the road" for place, name in seen)

    # The trajectories sidecar takes the same rule: at the key frame, each annotated object's code is its attribute.
    traj = load_trajectories(dataset, scene.name)
    keep = np.flatnonzero(objs.annotated)
    codes = traj.attributes[int(np.argmin(np.abs(traj.times_us - tables["sample"][0]["timestamp"])))]
    for ann in tables["sample_annotation"]:
        k = index_of[ann["instance_token"]]
        names = [attribute_name[a] for a in ann["attribute_tokens"]]
        assert ATTRIBUTE_NAMES[codes[int(np.searchsorted(keep, k))]] == (names[0] if names else "")
