"""PNG plots of the studies' results (matplotlib, Agg backend, imported when a plot is asked for)."""

from __future__ import annotations

from pathlib import Path

from streamdet.studies.calib_noise import CalibNoiseResult
from streamdet.studies.common import SHORT_CLASS
from streamdet.studies.drop_camera import DropCameraResult
from streamdet.studies.resolution import ResolutionResult
from streamdet.studies.slices import SlicesResult


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def plot_slices(result: SlicesResult, path: Path) -> None:
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(6, 4))
    x = list(range(len(result.slice_counts)))
    ax.plot(x, [100 * s.mean_ap for s in result.fused], "o-", label="fused (camera + LiDAR)")
    if result.baseline is not None:
        ax.plot(x, [100 * s.mean_ap for s in result.baseline], "s--", label="LiDAR-only baseline")
    ax.set_xticks(x, [str(n) for n in result.slice_counts])
    ax.set_xlabel("slices per sweep")
    ax.set_ylabel("mAP (%)")
    ax.set_ylim(bottom=0)
    ax.set_title(f"mAP vs slices ({result.num_samples} samples)")
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def plot_drop_camera(result: DropCameraResult, path: Path) -> None:
    plt = _pyplot()
    labels = ["mAP", *(SHORT_CLASS.get(c, c) for c in result.classes)]
    rows = [("all cameras", result.all_cameras), *((f"without {c}", s) for c, s in zip(result.cameras, result.without))]
    if result.no_cameras is not None:
        rows.append(("no camera at all", result.no_cameras))
    fig, ax = plt.subplots(figsize=(max(6.0, 0.8 * len(labels) * len(rows)), 4))
    width = 0.8 / len(rows)
    for k, (name, score) in enumerate(rows):
        values = [100 * score.mean_ap, *(100 * score.class_aps[c] for c in result.classes)]
        ax.bar([i + (k - (len(rows) - 1) / 2) * width for i in range(len(labels))], values, width, label=name)
    ax.set_xticks(range(len(labels)), labels)
    ax.set_ylabel("AP (%)")
    ax.set_title(f"A camera missing at inference ({result.num_slices} slices, {result.num_samples} samples)")
    ax.grid(axis="y", alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def plot_calib_noise(result: CalibNoiseResult, path: Path) -> None:
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(6, 4))
    x = list(range(len(result.levels)))
    ax.errorbar(x, [100 * lv.mean_ap for lv in result.levels], yerr=[100 * lv.std_ap for lv in result.levels],
                fmt="o-", capsize=4, label=f"noisy calibration (mean +- std, {len(result.seeds)} seeds)")  # fmt: skip
    ax.axhline(100 * result.reference.mean_ap, color="gray", ls="--", label="true calibration")
    top = max([result.reference.mean_ap, *(lv.mean_ap + lv.std_ap for lv in result.levels)])
    ax.set_ylim(0, max(1.0, 130 * top))  # headroom for the legend above the curve
    ax.set_xticks(x, [f"{lv.max_angle_deg:g} deg\n{100 * lv.max_translation_m:g} cm" for lv in result.levels])
    ax.set_xlabel("uniform extrinsic noise bound")
    ax.set_ylabel("mAP (%)")
    ax.set_title(f"mAP vs calibration noise ({result.num_slices} slices, {result.num_samples} samples)")
    ax.grid(alpha=0.3)
    ax.legend(loc="lower left")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def plot_resolution(result: ResolutionResult, path: Path) -> None:
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(6, 4))
    x = list(range(len(result.rows)))
    labels = [f"{r.width}x{r.height}" + ("*" if r.upsampled else "") for r in result.rows]
    ax.bar(x, [100 * r.score.mean_ap for r in result.rows], 0.5, color="tab:blue", label="mAP")
    ax.set_xticks(x, labels)
    ax.set_ylabel("mAP (%)", color="tab:blue")
    ax.set_xlabel("image size" + (" (* upsampled)" if any(r.upsampled for r in result.rows) else ""))
    twin = ax.twinx()
    twin.plot(x, [r.image_lane_p50_ms for r in result.rows], "o-", color="tab:red", label="image lane")
    twin.set_ylabel(f"image lane median ms ({result.num_cameras} cameras)", color="tab:red")
    twin.set_ylim(bottom=0)
    ax.set_title(f"mAP and image-lane latency vs resolution ({result.num_samples} samples)")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
