"""Holding a Ctrl-C back until a training step ends: a step interrupted half way leaves a state no checkpoint may
keep (streamdet-train and streamdet-train-image write last.pt of the last whole step on a Ctrl-C)."""

from __future__ import annotations

import signal
import threading
from collections.abc import Iterator
from contextlib import contextmanager


class InterruptedMidStep(KeyboardInterrupt):
    """A KeyboardInterrupt that ended a step half done (a second Ctrl-C while the first one waited for the step's
    end): nothing may be saved of that state."""


@contextmanager
def sigint_deferred() -> Iterator[None]:
    """Hold a Ctrl-C (SIGINT) back until the block (one training step and its bookkeeping) ends, then deliver it.

    A KeyboardInterrupt inside a step leaves its state half changed: the forward pass already moved the BatchNorm
    running statistics, the update can be half applied, or the weights of step n sit under the schedule and data
    position of step n - 1; a checkpoint of that, resumed, is not the uninterrupted run. A second Ctrl-C while the
    first waits is not held: it ends the block at once, as ``InterruptedMidStep``. Only the main thread takes signals;
    elsewhere, and where the SIGINT handler was installed from C (``getsignal`` gives None, which cannot be put
    back), the block runs as it is."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.getsignal(signal.SIGINT)  # read before hold can run
    if previous is None:
        yield
        return
    caught: list[int] = []

    def hold(signum: int, _frame) -> None:
        caught.append(signum)
        signal.signal(signal.SIGINT, previous)  # the next Ctrl-C goes through at once

    signal.signal(signal.SIGINT, hold)
    try:
        yield
    except KeyboardInterrupt as e:
        raise InterruptedMidStep(*e.args) from None
    finally:
        signal.signal(signal.SIGINT, previous)
    if caught:
        signal.raise_signal(signal.SIGINT)  # to the handler the process had: a KeyboardInterrupt, as a Ctrl-C gives
