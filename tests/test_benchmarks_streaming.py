"""The sequential-queue simulation's arithmetic on fake workloads, against a hand example and a naive reference."""

from __future__ import annotations

import numpy as np
import pytest

from streamdet.benchmarks.streaming import IMAGES, SLICE, Job, arrival_schedule, run_sequential_queue


def naive_queue(jobs, durations):
    """Reference: FIFO in arrival order; an image set is dropped if a newer one arrived by the time it would start."""
    order = sorted(range(len(jobs)), key=lambda i: jobs[i].arrival_ms)
    free = 0.0
    served, superseded = [], []
    for i in order:
        j = jobs[i]
        start = max(j.arrival_ms, free)
        if j.kind == IMAGES and any(o.kind == IMAGES and j.arrival_ms < o.arrival_ms <= start for o in jobs):
            superseded.append(j)
            continue
        free = start + durations[j]
        served.append((j, start, free))
    return served, superseded


def test_hand_example():
    jobs = [Job(SLICE, 0.0, 0), Job(IMAGES, 5.0, 0), Job(SLICE, 10.0, 1), Job(SLICE, 20.0, 2), Job(IMAGES, 30.0, 1), Job(IMAGES, 50.0, 2)]
    dur = {SLICE: 2.0, IMAGES: 100.0}
    run = run_sequential_queue(jobs, lambda j: dur[j.kind])
    got = [(s.job.kind, s.job.index, s.start_ms, s.finish_ms) for s in run.served]
    # image 1 waits behind image 0 and is replaced by image 2 (arrived at 50 <= 105) before it starts
    assert got == [(SLICE, 0, 0.0, 2.0), (IMAGES, 0, 5.0, 105.0), (SLICE, 1, 105.0, 107.0), (SLICE, 2, 107.0, 109.0), (IMAGES, 2, 109.0, 209.0)]
    assert [j.index for j in run.superseded] == [1]
    np.testing.assert_allclose(run.latencies(SLICE), [2.0, 97.0, 89.0])
    np.testing.assert_allclose(run.waits(SLICE), [0.0, 95.0, 87.0])
    np.testing.assert_allclose(run.latencies(IMAGES), [100.0, 159.0])


def test_idle_worker_jumps_to_next_arrival():
    jobs = [Job(SLICE, 0.0, 0), Job(SLICE, 100.0, 1)]
    run = run_sequential_queue(jobs, lambda j: 1.0)
    assert [(s.start_ms, s.finish_ms) for s in run.served] == [(0.0, 1.0), (100.0, 101.0)]
    assert run.waits(SLICE).tolist() == [0.0, 0.0]


@pytest.mark.parametrize("seed", range(8))
def test_matches_naive_reference(seed):
    rng = np.random.default_rng(seed)
    jobs = [Job(SLICE, float(t), k) for k, t in enumerate(np.sort(rng.uniform(0, 400, 30)))]
    jobs += [Job(IMAGES, float(t), i) for i, t in enumerate(np.sort(rng.uniform(0, 400, 6)))]
    rng.shuffle(jobs)  # input order must not matter
    durations = {j: float(rng.uniform(0.5, 15.0) if j.kind == SLICE else rng.uniform(20.0, 200.0)) for j in jobs}
    calls = []

    def process(job):
        calls.append(job)
        return durations[job]

    run = run_sequential_queue(jobs, process)
    ref_served, ref_superseded = naive_queue(jobs, durations)
    assert [s.job for s in run.served] == [r[0] for r in ref_served]
    np.testing.assert_allclose([s.start_ms for s in run.served], [r[1] for r in ref_served])
    np.testing.assert_allclose([s.finish_ms for s in run.served], [r[2] for r in ref_served])
    assert set(run.superseded) == set(ref_superseded)
    assert calls == [s.job for s in run.served]  # every served job ran exactly once, superseded ones never
    assert len(run.served) + len(run.superseded) == len(jobs)
    # a single worker never overlaps jobs
    starts = np.array([s.start_ms for s in run.served])
    finishes = np.array([s.finish_ms for s in run.served])
    assert np.all(starts[1:] >= finishes[:-1] - 1e-9)


def test_empty_and_bad_workload():
    run = run_sequential_queue([], lambda j: 1.0)
    assert run.served == () and run.superseded == ()
    assert run.latencies(SLICE).size == 0
    with pytest.raises(ValueError, match="duration in ms >= 0, got -1.0"):
        run_sequential_queue([Job(SLICE, 0.0, 0)], lambda j: -1.0)
    with pytest.raises(ValueError, match="got nan"):
        run_sequential_queue([Job(SLICE, 0.0, 0)], lambda j: float("nan"))


def test_arrival_schedule():
    jobs = arrival_schedule(num_slices=8, lidar_hz=10.0, image_hz=12.0, sweeps=2)
    slices = [j for j in jobs if j.kind == SLICE]
    images = [j for j in jobs if j.kind == IMAGES]
    assert len(slices) == 16 and [j.index for j in slices] == list(range(8)) * 2
    np.testing.assert_allclose([j.arrival_ms for j in slices], np.arange(16) * 12.5)
    assert len(images) == 3  # 0, 83.3, 166.7 ms inside the 200 ms horizon
    np.testing.assert_allclose([j.arrival_ms for j in images], np.arange(3) * 1000.0 / 12.0)
    assert [j.arrival_ms for j in jobs] == sorted(j.arrival_ms for j in jobs)
    assert jobs[0].kind == SLICE  # a slice before an image set at the same instant
    with pytest.raises(ValueError, match="num_slices, sweeps >= 1"):
        arrival_schedule(0, 10.0, 12.0, 1)
    with pytest.raises(ValueError, match="rates > 0"):
        arrival_schedule(8, 10.0, 0.0, 1)
