"""The benchmark's thread counts: by default every CPU this process may use (``core.cpu.usable_cpus``: affinity and
cgroup quota, not ``os.cpu_count()``), at most ``MAX_SESSION_THREADS``, the most one onnxruntime session takes
(core/constants.py says why). A machine with more CPUs than that runs its sessions at the cap instead of failing.
"""

from __future__ import annotations

from streamdet.core import cpu
from streamdet.core.constants import MAX_SESSION_THREADS


def default_session_threads(cpus: int | None = None) -> int:
    """Threads of one session when none are asked for: ``cpus`` (None: ``usable_cpus()``), clamped to
    1..MAX_SESSION_THREADS."""
    n = cpu.usable_cpus() if cpus is None else cpus
    return max(1, min(int(n), MAX_SESSION_THREADS))


def check_session_threads(value: object, name: str) -> int:
    """``value`` if it is an int in 1..MAX_SESSION_THREADS, else a one-line ValueError naming ``name``."""
    if isinstance(value, bool) or not isinstance(value, int) or not 1 <= value <= MAX_SESSION_THREADS:
        raise ValueError(f"{name} must be an int in 1..{MAX_SESSION_THREADS}, got {value!r}")
    return value
