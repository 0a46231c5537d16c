"""`WorkerLane`: a FIFO of jobs served by worker threads, the loop under every lane of the runtime (lanes.py) and
the replay's sequential queue. Bounded or not, with superseding jobs, joined runs (`JobBatching`, the slice lane's
coalescing) and spare workers (the slice lane borrowing the image lane's core between its updates)."""

from __future__ import annotations

import collections
import threading
import time
from concurrent.futures import Future, InvalidStateError
from dataclasses import dataclass
from typing import Callable, Sequence

from streamdet.runtime_ort.thread_priority import check_nice, start_worker

RUN_SAMPLES = 8  # runs whose second longest is `WorkerLane.run_s` (one outlier on a busy machine does not count)


class RunnerClosed(RuntimeError):
    """A submit after `StreamingRunner.close()`."""


@dataclass(frozen=True)
class JobBatching:
    """How a `WorkerLane` runs waiting jobs together (the slice lane's coalescing)."""

    joins: Callable[[object, object], bool]  # (payload of the run's last job, payload of the next waiting job)
    run: Callable[[list], Sequence[object]]  # payloads -> one result per payload, in order
    most: int  # jobs per run at most


class WorkerLane:
    """A FIFO served by worker threads.

    ``capacity``: how many jobs may wait beyond those the workers are about to take; when full, the oldest waiting
    job is failed with ``overflow()`` and counted in `dropped`. ``None``: unbounded, nothing is ever dropped.
    A job submitted with ``supersede`` replaces the waiting jobs of its ``kind`` (each failed with ``supersede()``
    and counted in `superseded`): one queue can carry slices that all run and image sets of which only the newest
    matters. A job a free worker is about to take counts as running, never as waiting.

    ``batch`` (optional) lets a worker take waiting jobs together: a job submitted with a ``payload`` joins the job
    a worker has just taken when no other worker is free, the two payloads ``batch.joins(previous, next)`` and the
    run holds fewer than ``batch.most`` jobs; ``batch.run(payloads)`` then does them in one call and returns one
    result per payload (counted in `joined`: the jobs that ran inside another's run).

    ``spare`` workers (optional) take a job only while all ``workers`` are busy and ``spare_gate()`` is true (read
    under the lane's lock: it must be quick and must not take a lock another thread holds while calling into this
    lane); a spare worker that is not allowed in is not free (the job waits, may be joined, may be dropped).
    `wake()` tells the spare workers that the gate may have opened; it closes by itself.
    """

    def __init__(self, name: str, workers: int, capacity: int | None, overflow: Callable[[], Exception] | None = None,
                 nice: int = 0, batch: "JobBatching | None" = None, spare: int = 0,
                 spare_gate: Callable[[], bool] | None = None, on_idle: Callable[[], None] | None = None) -> None:  # fmt: skip
        """``nice``: added to each worker thread's nice value (thread_priority.py); ``on_idle``: called (off the lock,
        on the worker's thread) when a run ends and no job runs or waits (the image lane waking the slice lane's spare
        workers)."""
        if capacity is not None and overflow is None:
            raise ValueError(f"{name}: a lane with a capacity ({capacity}) needs an overflow error")
        if spare and spare_gate is None:
            raise ValueError(f"{name}: {spare} spare worker(s) need a spare_gate (when they may take a job)")
        self._name = name
        self._jobs: collections.deque = collections.deque()  # (fn, future, kind, payload)
        self._batch = batch
        self.joined = 0
        self._cond = threading.Condition()
        self._capacity = capacity
        self._overflow = overflow
        self._closed = False
        self._workers = workers
        self._spare = spare
        self._gate = spare_gate
        self._on_idle = on_idle
        self._nice = check_nice(nice, f"{name}: nice")
        self._busy = 0  # workers (not spare) running a job (under _cond)
        self._busy_spare = 0  # spare workers running a job (under _cond)
        self.dropped = 0
        self.superseded = 0
        self.spare_runs = 0  # runs a spare worker did
        self.cpu_s = 0.0  # CPU seconds of the jobs run (thread time of their worker threads)
        self._run_s: collections.deque = collections.deque(maxlen=RUN_SAMPLES)  # wall seconds of the last runs
        self._threads: list[threading.Thread] = []
        try:
            for i in range(workers):
                self._threads.append(start_worker(lambda: self._serve(False), f"{name}-{i}", self._nice))
            for i in range(spare):
                self._threads.append(start_worker(lambda: self._serve(True), f"{name}-spare-{i}", self._nice))
        except OSError:  # the workers already started end at once
            self.close()
            raise

    def submit(self, fn: Callable[[], object], kind: str = "", supersede: Callable[[], Exception] | None = None,
               payload: object = None) -> Future:  # fmt: skip
        """``payload``: what `JobBatching` reads to run this job together with others (None: always alone)."""
        fut: Future = Future()
        with self._cond:
            if self._closed:
                raise RunnerClosed(f"{self._name}: submit after close()")
            # jobs the caller cancelled hold no place in the queue
            self._jobs = collections.deque(job for job in self._jobs if not job[1].cancelled())
            free = self._free()  # the first `free` jobs are about to start: in flight, not waiting
            if supersede is not None:
                stale = [job for job in list(self._jobs)[free:] if job[2] == kind]
                for job in stale:
                    self._jobs.remove(job)
                    self.superseded += self._fail(job[1], supersede)
            while self._capacity is not None and len(self._jobs) - free >= self._capacity:
                old = self._jobs[free]
                del self._jobs[free]
                self.dropped += self._fail(old[1], self._overflow)
            self._jobs.append((fn, fut, kind, payload))
            # a spare worker woken for a job it may not take would leave a free worker asleep: wake all
            if self._spare:
                self._cond.notify_all()
            else:
                self._cond.notify()
        return fut

    def _free(self) -> int:
        """(Under the lock.) Workers that would take a job now: the idle ones, and the idle spare ones while all
        others are busy and the gate is open."""
        idle = self._workers - self._busy
        if self._spare - self._busy_spare > 0 and self._gate():
            return idle + self._spare - self._busy_spare
        return idle

    def _may_take(self, spare: bool) -> bool:
        """(Under the lock.) May a worker of this kind take the first waiting job now?"""
        if not self._jobs:
            return False
        return not spare or (self._busy >= self._workers and self._gate())

    def wake(self) -> None:
        """The spare workers' gate may have opened: those waiting look again (a no-op without spare workers)."""
        if self._spare:
            with self._cond:
                if self._jobs:
                    self._cond.notify_all()

    @property
    def waiting(self) -> int:
        """Jobs waiting beyond those the workers run or are about to take (cancelled ones included until the next
        submit clears them)."""
        with self._cond:
            return max(0, len(self._jobs) - self._free())

    @property
    def queued(self) -> int:
        """Jobs in the queue, those a free worker is about to take included. Read without the lock, so that a
        ``spare_gate`` (which runs under it) may read it: a hint that may be a moment old."""
        return len(self._jobs)

    @property
    def run_s(self) -> float:
        """Wall seconds of a run, the second longest of the last few (0 before the first)."""
        with self._cond:
            ordered = sorted(self._run_s)
        return ordered[-2] if len(ordered) >= 2 else (ordered[-1] if ordered else 0.0)

    @staticmethod
    def _fail(fut: Future, error: Callable[[], Exception]) -> int:
        """Fail a waiting job's future; 1 when it was failed, 0 when its owner had cancelled it meanwhile."""
        try:
            fut.set_exception(error())
            return 1
        except InvalidStateError:  # cancelled by its owner meanwhile: nothing to tell anyone
            return 0

    def _serve(self, spare: bool) -> None:
        while True:
            with self._cond:
                while not self._closed and not self._may_take(spare):
                    self._cond.wait()
                if not self._may_take(spare):  # closed: the other workers finish what is left
                    return
                jobs = [self._jobs.popleft()]
                if spare:
                    self._busy_spare += 1
                    self.spare_runs += 1
                else:
                    self._busy += 1
                try:
                    self._join_waiting(jobs)
                    join_error = None
                except Exception as e:  # a failing join rule must not end the worker: its jobs get the error
                    join_error = e
            cpu0 = time.thread_time()
            t0 = time.perf_counter()
            try:
                jobs = [job for job in jobs if job[1].set_running_or_notify_cancel()]
                if join_error is not None:
                    for job in jobs:
                        job[1].set_exception(join_error)
                elif len(jobs) == 1:
                    fn, fut = jobs[0][:2]
                    try:
                        fut.set_result(fn())
                    except BaseException as e:  # handed to the caller through the future, never swallowed
                        fut.set_exception(e)
                elif jobs:
                    self._run_joined(jobs)
            finally:
                with self._cond:
                    if spare:
                        self._busy_spare -= 1
                    else:
                        self._busy -= 1
                    self.cpu_s += time.thread_time() - cpu0
                    if jobs:
                        self._run_s.append(time.perf_counter() - t0)
                    now_idle = not self._jobs and self._busy == 0 and self._busy_spare == 0
            if now_idle and self._on_idle is not None:
                self._on_idle()

    def _join_waiting(self, jobs: list) -> None:
        """(Under the lock.) Move the waiting jobs that may run with ``jobs[-1]`` into ``jobs``: only while no other
        worker is free to take them, so joining never idles a core that could have run a job alone."""
        b = self._batch
        if b is None or jobs[0][3] is None:
            return
        while len(jobs) < b.most and self._jobs and self._free() <= 0:
            nxt = self._jobs[0]
            if nxt[1].cancelled():  # holds no place (as in submit)
                self._jobs.popleft()
                continue
            if nxt[3] is None or not b.joins(jobs[-1][3], nxt[3]):
                return
            jobs.append(self._jobs.popleft())

    def _run_joined(self, jobs: list) -> None:
        """Run jobs that `_join_waiting` put together in one ``batch.run`` call; its error goes to every job."""
        try:
            results = list(self._batch.run([job[3] for job in jobs]))
            if len(results) != len(jobs):
                raise RuntimeError(f"{self._name}: a joined run of {len(jobs)} jobs returned {len(results)} results")
        except BaseException as e:  # handed to the callers through the futures, never swallowed
            for job in jobs:
                job[1].set_exception(e)
            return
        for job, result in zip(jobs, results):
            job[1].set_result(result)
        with self._cond:
            self.joined += len(jobs) - 1

    @property
    def idle(self) -> bool:
        """No job runs or waits. Read without the lock (another lane's gate reads it under its own lock): a hint
        that may be a moment old, never a torn value."""
        return not self._jobs and self._busy == 0 and self._busy_spare == 0

    def close(self, deadline: float | None = None) -> bool:
        """Stop taking jobs, finish the queued ones by ``deadline`` (time.monotonic(); None: no limit). Past it, the
        jobs not started are cancelled; True when every worker has ended."""
        with self._cond:
            self._closed = True
            self._cond.notify_all()
        for t in self._threads:
            t.join(None if deadline is None else max(0.0, deadline - time.monotonic()))
        if all(not t.is_alive() for t in self._threads):
            return True
        with self._cond:
            while self._jobs:
                self._jobs.popleft()[1].cancel()
        return False
