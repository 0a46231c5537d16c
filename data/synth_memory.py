"""What ``streamdet-synth generate`` needs in memory, and whether the machine has it (refused before any work).

The renderer holds per-pixel arrays of all six cameras of a frame at once (ray directions, depths, colours, object
ids and the candidate pixels of each part), so a process's peak grows linearly with the image's pixels; each
``--workers`` process simulates a scene of its own and peaks as much. The constants bound that growth from above,
with a margin over what docs/synth/memory.md measured; the largest accepted resolution needs several GB per process.
"""

from __future__ import annotations

from pathlib import Path

try:
    import resource  # Unix only: elsewhere no address-space limit is read
except ImportError:  # pragma: no cover (Windows)
    resource = None

# Peak bytes of one simulating process: a fixed part (Python, numpy, OpenCV, the scene, LiDAR sweeps) and a part per
# pixel of the images (six cameras' renders and their temporaries). Bounds above the measurements in
# docs/synth/memory.md, so a refusal is not a close call.
PEAK_BASE_BYTES = 250 * 2**20
PEAK_BYTES_PER_PIXEL = 600
# Address space a process maps beyond what it touches (thread arenas, shared libraries): what an address-space limit
# (ulimit -v) sees on top of the resident peak.
ADDRESS_SPACE_SLACK_BYTES = 1 << 30
# A cgroup or rlimit at or above this is "no limit" (cgroup v1 writes 2**63 rounded down to a page).
_NO_LIMIT = 1 << 60


def peak_bytes_per_process(resolution: tuple[int, int]) -> int:
    """Upper estimate of one simulating process's peak resident memory at ``resolution`` (width, height)."""
    w, h = resolution
    return PEAK_BASE_BYTES + PEAK_BYTES_PER_PIXEL * int(w) * int(h)


def processes(workers: int, num_scenes: int) -> int:
    """Processes that simulate at once: one per scene up to ``workers`` (``generate_dataset``)."""
    return max(1, min(int(workers), int(num_scenes)))


def peak_bytes(resolution: tuple[int, int], workers: int, num_scenes: int) -> int:
    """Upper estimate of the whole run's peak: every simulating process at its peak, plus the parent that waits for
    them when there are several."""
    n = processes(workers, num_scenes)
    return n * peak_bytes_per_process(resolution) + (PEAK_BASE_BYTES if n > 1 else 0)


def available_memory() -> tuple[int | None, int | None]:
    """(bytes the run may still use in all, address space one process may map), None where unknown or unlimited.

    The first is the least of the kernel's estimate of memory available without swapping (Linux MemAvailable) and
    what is left under this process's cgroup limit (v2 or v1), which is what kills a container; the second is the
    soft address-space limit (``ulimit -v``), which numpy meets as a MemoryError."""
    candidates = [_meminfo_available(), _cgroup_left()]
    known = [c for c in candidates if c is not None]
    total = min(known) if known else None
    if resource is None:
        return total, None
    soft, _ = resource.getrlimit(resource.RLIMIT_AS)
    per_process = None if soft == resource.RLIM_INFINITY or soft >= _NO_LIMIT else int(soft)
    return total, per_process


def memory_problem(resolution: tuple[int, int], workers: int, num_scenes: int) -> str | None:
    """Why a run at ``resolution`` with ``workers`` processes would run out of memory (one line naming the options),
    or None where it fits or the machine does not say what it has."""
    w, h = resolution
    n = processes(workers, num_scenes)
    total, per_process = available_memory()
    need = peak_bytes(resolution, workers, num_scenes)
    options = f"--resolution {w}x{h} with --workers {workers}"
    if workers > 1:
        options += f" ({n} scene(s) simulated at once)"
    per_gb = PEAK_BYTES_PER_PIXEL * 1e6 / 1e9
    hint = (f"each simulating process needs about {per_gb:.1f} GB per megapixel of image; choose a lower --resolution"
            + (" or fewer --workers" if n > 1 else ""))
    if total is not None and need > total:
        return f"{options} needs about {_gb(need)} of memory, more than the {_gb(total)} available: {hint}"
    if per_process is not None and peak_bytes_per_process(resolution) + ADDRESS_SPACE_SLACK_BYTES > per_process:
        need_as = peak_bytes_per_process(resolution) + ADDRESS_SPACE_SLACK_BYTES
        return (f"{options} needs about {_gb(need_as)} of address space per process, more than the limit of "
                f"{_gb(per_process)} (ulimit -v): {hint}")
    return None


def _gb(n: int) -> str:
    return f"{n / 1e9:.1f} GB"


def _meminfo_available(path: Path = Path("/proc/meminfo")) -> int | None:
    try:
        for line in path.read_text().splitlines():
            if line.startswith("MemAvailable:"):
                return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    return None  # not Linux, or a kernel without the field: unknown, so nothing is refused on its account


def _cgroup_left(base: Path = Path("/sys/fs/cgroup")) -> int | None:
    """What the memory cgroup the file system shows still allows (limit less its working set, i.e. usage less the
    inactive page cache the kernel reclaims before it kills anything, as container runtimes count it; in a
    container, its own group), None without a limit."""
    v1 = ("memory/memory.limit_in_bytes", "memory/memory.usage_in_bytes", "memory/memory.stat", "total_inactive_file")
    for limit_file, usage_file, stat_file, inactive_key in (("memory.max", "memory.current", "memory.stat", "inactive_file"), v1):
        try:
            limit = (base / limit_file).read_text().strip()
            usage = int((base / usage_file).read_text().strip())
        except (OSError, ValueError):
            continue
        if limit == "max" or not limit.isdigit() or int(limit) >= _NO_LIMIT:
            return None
        return max(0, int(limit) - max(0, usage - _stat_value(base / stat_file, inactive_key)))
    return None


def _stat_value(path: Path, key: str) -> int:
    """``key``'s value in a cgroup memory.stat file (bytes), 0 where the file or the key is missing."""
    try:
        for line in path.read_text().splitlines():
            name, _, value = line.partition(" ")
            if name == key:
                return int(value)
    except (OSError, ValueError):
        pass
    return 0

