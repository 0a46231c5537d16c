"""`WorkerLane`: a FIFO of jobs served by worker threads, the loop under every lane of the runtime (lanes.py) and
the replay's sequential queue: bounded or not, with superseding jobs and joined runs (`JobBatching`, the slice
lane's coalescing)."""

from __future__ import annotations

import collections
import logging
import threading
import time
from concurrent.futures import Future, InvalidStateError
from dataclasses import dataclass
from typing import Callable, Sequence

from streamdet.runtime_ort.thread_priority import check_nice, start_worker

log = logging.getLogger(__name__)


class RunnerClosed(RuntimeError):
    """A submit after `StreamingRunner.close()`."""


@dataclass(frozen=True)
class JobBatching:
    """How a `WorkerLane` runs waiting jobs together (the slice lane's coalescing)."""

    joins: Callable[[object, object], bool]  # (payload of the run's last job, payload of the next waiting job)
    run: Callable[[list], Sequence[object]]  # payloads -> one result per payload, in order
    most: int  # jobs per run at most
    # seconds a worker that has taken a job (payload) waits for a job to join it before it runs alone; 0: it runs at once.
    # A job that would join a waiting worker's run is left to it by the other workers. None: never waits
    # (LaneConfig.pair_hold_load, runtime_ort/pair_hold.py).
    hold: Callable[[object], float] | None = None
    # (payloads of a run with the next job's added) -> may they run together; None: any that join may. What a pairwise
    # ``joins`` cannot see: the run's total (the slice lane's points, MAX_SLICE_POINTS for the slices of one run).
    fits: Callable[[list], bool] | None = None


class WorkerLane:
    """A FIFO served by worker threads.

    ``capacity``: how many jobs may wait beyond those the workers are about to take; when full, the oldest waiting
    job is failed with ``overflow()`` and counted in `dropped`. ``None``: unbounded, nothing is ever dropped.
    A job submitted with ``supersede`` replaces the waiting jobs of its ``kind`` (each failed with ``supersede()``
    and counted in `superseded`): one queue can carry slices that all run and image sets of which only the newest
    matters. A job an idle worker is about to take counts as running, never as waiting.

    ``batch`` (optional) lets a worker take waiting jobs together: a job submitted with a ``payload`` joins the job
    a worker has just taken when no other worker is free, the two payloads ``batch.joins(previous, next)`` and the
    run holds fewer than ``batch.most`` jobs; ``batch.run(payloads)`` then does them in one call and returns one
    result per payload (counted in `joined`: the jobs that ran inside another's run). With ``batch.hold``, a worker
    whose job has no joining job waiting may wait that long for one to arrive (counted in `held`) before it runs.
    """

    def __init__(self, name: str, workers: int, capacity: int | None, overflow: Callable[[], Exception] | None = None,
                 nice: int = 0, batch: "JobBatching | None" = None) -> None:  # fmt: skip
        """``nice``: added to each worker thread's nice value (thread_priority.py)."""
        if capacity is not None and overflow is None:
            raise ValueError(f"{name}: a lane with a capacity ({capacity}) needs an overflow error")
        self._name = name
        self._jobs: collections.deque = collections.deque()  # (fn, future, kind, payload)
        self._batch = batch
        self.joined = 0
        self.held = 0  # runs whose first job waited for a job to join it (batch.hold)
        self._holding: list = []  # the last job of each run a worker is waiting to join (under _cond)
        self._cond = threading.Condition()
        self._capacity = capacity
        self._overflow = overflow
        self._closed = False
        self._deadline: float | None = None  # close(deadline): jobs not started by then are cancelled by the workers
        self._expired = 0  # jobs the workers cancelled so (close() then reports that not everything ran)
        self._workers = workers
        self._nice = check_nice(nice, f"{name}: nice")
        self._busy = 0  # workers running a job (under _cond)
        self.dropped = 0
        self.superseded = 0
        self.cpu_s = 0.0  # CPU seconds of the jobs run (thread time of their worker threads)
        self._threads: list[threading.Thread] = []
        try:
            for i in range(workers):
                self._threads.append(start_worker(self._serve, f"{name}-{i}", self._nice))
        except OSError:  # the workers already started end at once
            self.close()
            raise

    def submit(self, fn: Callable[[], object], kind: str = "", supersede: Callable[[], Exception] | None = None,
               payload: object = None) -> Future:  # fmt: skip
        """``payload``: what `JobBatching` reads to run this job together with others (None: always alone).

        Never raises for another job: the jobs it drops or supersedes are counted and taken off the queue under the
        lock, and their futures are failed after it is released, each done-callback's error logged (a callback may
        be slow, call close(), or raise SystemExit: none of that may stall the workers or lose this job)."""
        fut: Future = Future()
        with self._cond:
            if self._closed:
                raise RunnerClosed(f"{self._name}: submit after close()")
            # jobs the caller cancelled hold no place in the queue (claimed: concurrent.futures.wait sees them done)
            kept: collections.deque = collections.deque()
            for job in self._jobs:
                if not job[1].cancelled():
                    kept.append(job)
                else:
                    claim_future(job[1])  # False
            self._jobs = kept
            idle = self._workers - self._busy  # the first `idle` jobs are about to start: in flight, not waiting
            failed: list[tuple[Future, Callable[[], Exception]]] = []  # failed once the lock is released
            if supersede is not None:
                stale = [job for job in list(self._jobs)[idle:] if job[2] == kind]
                for job in stale:
                    self._jobs.remove(job)
                    if claim_future(job[1]):
                        self.superseded += 1
                        failed.append((job[1], supersede))
            while self._capacity is not None and len(self._jobs) - idle >= self._capacity:
                old = self._jobs[idle]
                del self._jobs[idle]
                if claim_future(old[1]):
                    self.dropped += 1
                    failed.append((old[1], self._overflow))
            self._jobs.append((fn, fut, kind, payload))
            if self._holding:  # the worker waiting for this job must wake, not only an idle one
                self._cond.notify_all()
            else:
                self._cond.notify()
        for job_fut, error in failed:
            complete_future(self._name, job_fut, error=error())
        return fut

    @property
    def waiting(self) -> int:
        """Jobs waiting beyond those the workers run or are about to take; jobs their owners cancelled do not count
        (they stay queued until the next submit or a worker clears them, but nobody waits for them)."""
        with self._cond:
            live = sum(1 for job in self._jobs if not job[1].cancelled())  # a worker skips a cancelled one
            return max(0, live - (self._workers - self._busy))

    def _serve(self) -> None:
        while True:
            with self._cond:
                while (not self._jobs or self._reserved(self._jobs[0])) and not self._closed:
                    self._cond.wait()
                if not self._jobs:
                    return
                if self._closed and self._deadline is not None and time.monotonic() >= self._deadline:
                    expired, self._jobs = list(self._jobs), collections.deque()  # not started by close()'s deadline
                    self._expired += sum(1 for job in expired if not job[1].cancelled())  # their owners' own: not counted
                else:
                    expired = None
                    jobs = [self._jobs.popleft()]
                    self._busy += 1
                    try:
                        self._join_waiting(jobs)
                        if len(jobs) == 1:
                            self._hold_for_join(jobs)
                        join_error = None
                    except BaseException as e:  # a failing join rule must not end the worker: its jobs get the error
                        join_error = e
            if expired is not None:
                for job in expired:  # off the lock: their done-callbacks run here
                    cancel_future(self._name, job[1])
                return
            cpu0 = time.thread_time()
            try:
                jobs = [job for job in jobs if claim_future(job[1])]
                if join_error is not None:
                    for job in jobs:
                        complete_future(self._name, job[1], error=join_error)
                elif len(jobs) == 1:
                    fn, fut = jobs[0][:2]
                    try:
                        result = fn()
                    except BaseException as e:  # handed to the caller through the future, never swallowed
                        complete_future(self._name, fut, error=e)
                    else:  # outside the try: a done-callback's error is no error of the job's
                        complete_future(self._name, fut, result)
                elif jobs:
                    self._run_joined(jobs)
            finally:
                with self._cond:
                    self._busy -= 1
                    self.cpu_s += time.thread_time() - cpu0

    def _join_waiting(self, jobs: list) -> None:
        """(Under the lock.) Move the waiting jobs that may run with ``jobs[-1]`` into ``jobs``: only while no other
        worker is free to take them, so joining never idles a core that could have run a job alone."""
        b = self._batch
        if b is None or jobs[0][3] is None:
            return
        while len(jobs) < b.most and self._busy >= self._workers:
            if not self._may_join(jobs, self._next_waiting()):
                return
            jobs.append(self._jobs.popleft())

    def _may_join(self, jobs: list, nxt: tuple | None) -> bool:
        """(Under the lock.) May the waiting job ``nxt`` run in the run ``jobs``? (``batch.joins`` and ``batch.fits``)"""
        b = self._batch
        if nxt is None or nxt[3] is None or not b.joins(jobs[-1][3], nxt[3]):
            return False
        return b.fits is None or bool(b.fits([job[3] for job in jobs] + [nxt[3]]))

    def _reserved(self, job: tuple) -> bool:
        """(Under the lock.) Would ``job`` join the run of a worker that is waiting for one? Then it is that worker's."""
        if not self._holding or job[3] is None:
            return False
        try:
            return any(self._batch.joins(held[3], job[3]) for held in self._holding)
        except BaseException:  # a failing join rule: the job is nobody's reserve (the holder's own call fails its run)
            return False

    def _hold_for_join(self, jobs: list) -> None:
        """(Under the lock.) Wait, as ``batch.hold`` says, for a job to join ``jobs[-1]``; add it and whatever may join
        after it, up to ``batch.most``. The wait ends at once on close."""
        b = self._batch
        while b is not None and b.hold is not None and len(jobs) < b.most and jobs[-1][3] is not None and not self._closed:
            wait_s = b.hold(jobs[-1][3])
            if not wait_s > 0:  # no hold: joining stays as `_join_waiting` does it
                return
            deadline = time.monotonic() + wait_s
            if not self._next_waiting():
                self.held += 1
                self._holding.append(jobs[-1])
                try:
                    while not self._next_waiting() and not self._closed:
                        left = deadline - time.monotonic()
                        if left <= 0:
                            break
                        self._cond.wait(left)
                finally:
                    self._holding = [job for job in self._holding if job is not jobs[-1]]
                    if self._jobs:  # an idle worker that left the reserved job alone may take the ones behind it
                        self._cond.notify()
            if not self._may_join(jobs, self._next_waiting()):
                return
            jobs.append(self._jobs.popleft())

    def _next_waiting(self) -> tuple | None:
        """(Under the lock.) The first waiting job its owner has not cancelled (cancelled ones hold no place, as in
        submit: they are dropped)."""
        while self._jobs and self._jobs[0][1].cancelled():
            claim_future(self._jobs.popleft()[1])  # False; concurrent.futures.wait now sees it done
        return self._jobs[0] if self._jobs else None

    def _run_joined(self, jobs: list) -> None:
        """Run jobs that `_join_waiting` put together in one ``batch.run`` call; its error goes to every job."""
        try:
            results = list(self._batch.run([job[3] for job in jobs]))
            if len(results) != len(jobs):
                raise RuntimeError(f"{self._name}: a joined run of {len(jobs)} jobs returned {len(results)} results")
        except BaseException as e:  # handed to the callers through the futures, never swallowed
            for job in jobs:
                complete_future(self._name, job[1], error=e)
            return
        for job, result in zip(jobs, results):  # outside the try: a done-callback's error is no error of the run's
            complete_future(self._name, job[1], result)
        with self._cond:
            self.joined += len(jobs) - 1

    def stop(self) -> None:
        """Stop taking jobs without waiting: the workers end once the queued jobs are done (their futures complete).
        For a lane whose owner is gone (StreamingRunner's finalizer): this may run on any thread, a worker's too."""
        self.close(wait=False)

    def runs_on(self, thread: threading.Thread) -> bool:
        """Whether ``thread`` is one of this lane's workers."""
        return thread in self._threads

    def close(self, deadline: float | None = None, wait: bool = True) -> bool:
        """Stop taking jobs, finish the queued ones by ``deadline`` (time.monotonic(); None: no limit). Past it, the
        jobs not started are cancelled. Jobs still queued once every worker has ended (workers that died: nobody is
        left to run them) fail with a RuntimeError, so that nobody waits on them forever. True when every worker has
        ended and every job ran (or was cancelled by its owner).

        ``wait`` False, or a call from one of this lane's own workers (a future's done-callback run there), does not
        wait for the calling worker: the workers run the queued jobs, except those not started by ``deadline``, which
        they cancel (a later close() then returns False too: not every job ran); this returns False (``wait`` False joins no worker at all: StreamingRunner.close on a worker of
        any of its lanes, where two callbacks closing at once would otherwise wait for each other)."""
        with self._cond:
            self._closed = True
            if deadline is not None:
                self._deadline = deadline if self._deadline is None else min(self._deadline, deadline)
            self._cond.notify_all()
        if not wait:
            return False
        me = threading.current_thread()
        for t in self._threads:
            if t is not me:  # called from a done-callback on a worker: that worker cannot wait for itself
                t.join(None if deadline is None else max(0.0, deadline - time.monotonic()))
        ended = all(not t.is_alive() for t in self._threads)
        if me in self._threads and (deadline is None or deadline > time.monotonic()):
            # the calling worker runs the queued jobs once its callback returns, then ends: nothing to cancel yet
            return False
        with self._cond:
            left = [job for job in self._jobs if not job[1].done()]
            for job in self._jobs:  # cancelled (or finished) by their owners: as they are, the cancelled ones claimed
                if job[1].done():
                    claim_future(job[1])  # False; concurrent.futures.wait sees a cancelled one done
            self._jobs.clear()
        for job in left:  # outside the lock: their done-callbacks run here
            if ended:
                error = RuntimeError(f"{self._name}: no worker left to run this job (they ended before it)")
                complete_future(self._name, job[1], error=error)
            else:
                cancel_future(self._name, job[1])
        with self._cond:
            expired = self._expired
        return ended and not left and not expired


def claim_future(fut: Future) -> bool:
    """Future.set_running_or_notify_cancel that never raises and runs no done-callback, so it may be called under a
    lane's lock: True when ``fut`` is now this lane's to complete (its owner can no longer cancel it); False for a
    future its owner cancelled, or finished (set_result on a future it was handed), which is left as it is.

    A lane calls it once on every future it takes off its books, cancelled ones too: `Future.cancel` alone leaves a
    future that ``concurrent.futures.wait`` and ``as_completed`` never see done; this call tells them (an executor's
    worker does the same when it reaches a cancelled job)."""
    if fut.done() and not fut.cancelled():  # finished by its owner: set_running_or_notify_cancel would log a critical
        return False
    try:
        return fut.set_running_or_notify_cancel()
    except RuntimeError:  # finished by its owner: "Future in unexpected state"
        return False


def complete_future(lane: str, fut: Future, result: object = None, error: BaseException | None = None) -> None:
    """Hand a job's result or error to its future. Never raises: a done-callback's error (a BaseException, say
    sys.exit() in a handler, escapes Future.set_result once the future is done) is logged rather than allowed to end
    the thread completing it (a worker, whose later jobs would then wait forever, or a submitter, whose own job would
    be lost); a future its owner finished meanwhile keeps its state. Call it with no lane lock held: callbacks run
    here."""
    try:
        if error is None:
            fut.set_result(result)
        else:
            fut.set_exception(error)
    except InvalidStateError:  # cancelled or finished by its owner meanwhile: nothing to tell anyone
        pass
    except BaseException:  # a done-callback's: the future is done, the lane goes on
        log.exception("%s: a done-callback of %r raised; the lane goes on", lane, fut)


def cancel_future(lane: str, fut: Future) -> None:
    """Future.cancel, a done-callback's error logged (as in `complete_future`), then claimed (`claim_future`), so
    that ``concurrent.futures.wait`` sees it done. With no lane lock held; for a future the lane still holds."""
    try:
        fut.cancel()
    except BaseException:
        log.exception("%s: a done-callback of %r raised; the lane goes on", lane, fut)
    if fut.cancelled():
        claim_future(fut)
