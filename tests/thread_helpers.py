"""Test helper (not a test module): calling something that must not block, with a deadline."""

from __future__ import annotations

import threading


def returns_within(fn, seconds: float):
    """fn() on a daemon thread; its result (or its exception, raised here), or a failure when it has not returned
    within ``seconds`` (a deadlock or a hang)."""
    out: dict = {}

    def run() -> None:
        try:
            out["result"] = fn()
        except BaseException as e:  # noqa: BLE001  # handed to the test
            out["error"] = e

    t = threading.Thread(target=run, daemon=True)
    t.start()
    t.join(seconds)
    assert not t.is_alive(), f"{fn} still running after {seconds} s: a deadlock or a hang"
    if "error" in out:
        raise out["error"]
    return out.get("result")
