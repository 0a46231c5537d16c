"""Kept for code that imports ``format_latency`` from here; ``streamdet-run`` is ``streamdet.evaluation.run_cli``
(it writes a nuScenes results file, which belongs to evaluation/) and the table is in ``runtime_ort.stats``."""

from streamdet.runtime_ort.stats import format_latency  # noqa: F401
