"""How long a 30k-point ``sensor_msgs/PointCloud2`` takes to become the runtime's sweep, and then its slices.

    python -m streamdet.benchmarks.ros_pointcloud2 [--points 30000] [--repeats 300]

Three layouts: the one ``streamdet-bag export`` writes (six little-endian float32 fields), an Ouster-like one
(float32 x y z, padding, uint16 intensity, uint32 ``t`` nanoseconds, uint16 ring, 48-byte points) and a
big-endian float64 one with NaN returns. Each is timed ``--repeats`` times after warm-up runs; the median, p95,
min and max are printed, for the decode alone and for decode + ``split_cloud`` into 8 slices. The issue's target is
under 2 ms for the decode of 30k points; results go to docs/ros2.md with the machine's load at the time.
"""

from __future__ import annotations

import time

import click
import numpy as np

from streamdet.runtime_ort.ros.pointcloud2 import CloudFields, decode_pointcloud2, split_cloud


class _Msg:
    """An attribute bag, as the ROS readers decode messages."""

    def __init__(self, **kw) -> None:
        self.__dict__.update(kw)


def _cloud(layout: str, n: int, rng: np.random.Generator) -> _Msg:
    xyz = rng.uniform(-50, 50, (n, 3))
    if layout == "streamdet":
        names, formats, offsets, step, big = ["x", "y", "z", "intensity", "ring", "time"], ["<f4"] * 4 + ["<u2", "<f4"], [0, 4, 8, 12, 16, 20], 24, False
        types = [7, 7, 7, 7, 4, 7]  # pointcloud2_message's: the ring a uint16
    elif layout == "ouster":
        names = ["x", "y", "z", "intensity", "t", "reflectivity", "ring", "ambient", "range"]
        formats = ["<f4", "<f4", "<f4", "<u2", "<u4", "<u2", "<u2", "<u2", "<u4"]
        offsets, step, big = [0, 4, 8, 16, 20, 24, 26, 28, 32], 48, False
        types = [7, 7, 7, 4, 6, 4, 4, 4, 6]
    else:  # big-endian float64 with NaN returns
        names, formats, offsets, step, big = ["x", "y", "z", "intensity", "timestamp"], [">f8"] * 5, [0, 8, 16, 24, 32], 40, True
        types = [8] * 5
    rec = np.zeros(n, dtype=np.dtype({"names": names, "formats": formats, "offsets": offsets, "itemsize": step}))
    rec["x"], rec["y"], rec["z"] = xyz.T
    rec["intensity"] = rng.integers(0, 256, n)
    time_name = {"streamdet": "time", "ouster": "t"}.get(layout, "timestamp")
    rec[time_name] = rng.integers(0, 50_000_000, n) if layout == "ouster" else rng.uniform(-0.05, 0, n)
    if layout == "float64_be":
        rec["x"][rng.choice(n, n // 20, replace=False)] = np.nan
    fields = [_Msg(name=nm, offset=o, datatype=t, count=1) for nm, o, t in zip(names, offsets, types)]
    header = _Msg(stamp=_Msg(sec=1_700_000_000, nanosec=0), frame_id="lidar")
    return _Msg(header=header, height=1, width=n, fields=fields, is_bigendian=big, point_step=step, row_step=step * n,
                data=rec.tobytes(), is_dense=layout != "float64_be")  # fmt: skip


def _time_ms(fn, repeats: int) -> np.ndarray:
    for _ in range(min(20, repeats)):
        fn()
    out = np.empty(repeats)
    for i in range(repeats):
        t0 = time.perf_counter()
        fn()
        out[i] = (time.perf_counter() - t0) * 1e3
    return out


@click.command(context_settings={"help_option_names": ["-h", "--help"]})
@click.option("--points", type=int, default=30_000, show_default=True, help="Points per cloud.")
@click.option("--repeats", type=int, default=300, show_default=True, help="Timed runs per measurement.")
@click.option("--slices", type=int, default=8, show_default=True, help="Slices per sweep for the decode + split rows.")
def main(points: int, repeats: int, slices: int) -> None:
    """Time PointCloud2 -> sweep (and -> slices) for three driver layouts."""
    rng = np.random.default_rng(0)
    click.echo(f"{'layout':<12}{'what':<16}{'median ms':>10}{'p95 ms':>9}{'min ms':>9}{'max ms':>9}")
    for layout in ("streamdet", "ouster", "float64_be"):
        msg = _cloud(layout, points, rng)
        fields = CloudFields()
        rows = {
            "decode": _time_ms(lambda: decode_pointcloud2(msg, fields), repeats),
            f"decode+split{slices}": _time_ms(lambda: split_cloud(decode_pointcloud2(msg, fields), slices), repeats),
        }
        for what, ms in rows.items():
            click.echo(f"{layout:<12}{what:<16}{np.median(ms):>10.3f}{np.percentile(ms, 95):>9.3f}{ms.min():>9.3f}{ms.max():>9.3f}")


if __name__ == "__main__":
    main()
