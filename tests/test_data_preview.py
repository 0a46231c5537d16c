"""Preview pictures (data/preview.py) and the streamdet-synth CLI."""

from __future__ import annotations

import numpy as np
import pytest
from click.testing import CliRunner

from streamdet.core.slicing import split_sweep
from streamdet.data.preview import (
    CLASS_COLORS_BGR,
    camera_mosaic,
    draw_bev,
    draw_camera_boxes,
    slice_colors_bgr,
    write_previews,
)
from streamdet.data.sample import load_bundled_sample, load_image
from streamdet.data.synth_cli import main


@pytest.fixture(scope="module")
def sample():
    return load_bundled_sample()


def test_bev_colours_points_by_slice(sample):
    pts = np.concatenate(split_sweep(sample.points, 8))  # (N, 6)
    image = draw_bev(pts, slice_of_point=pts[:, 5], n_slices=8, range_m=50.0, size_px=400)
    assert image.shape == (400, 400, 3) and image.dtype == np.uint8
    colors = slice_colors_bgr(8)
    assert len({tuple(c) for c in colors}) == 8
    # a point far from the grid lines shows in its slice's colour
    for k in range(8):
        p = pts[(pts[:, 5] == k) & (np.hypot(pts[:, 0], pts[:, 1]) > 12) & (np.hypot(pts[:, 0], pts[:, 1]) < 45)]
        col = np.floor(p[:, 0] * 4 + 200).astype(int)
        row = np.floor(200 - p[:, 1] * 4).astype(int)
        hits = np.all(image[row, col] == colors[k], axis=1)
        assert hits.mean() > 0.5, k


def test_bev_draws_boxes_and_detections(sample):
    blank = draw_bev(np.zeros((0, 6)), size_px=300)
    with_gt = draw_bev(np.zeros((0, 6)), sample.gt_boxes, sample.gt_labels, size_px=300)
    assert (with_gt != blank).any(axis=2).sum() > 200
    det = sample.gt_boxes[:5].copy()
    with_det = draw_bev(np.zeros((0, 6)), det_boxes=det, det_scores=np.array([0.9, 0.8, 0.7, 0.2, 0.1]), size_px=300,
                        score_threshold=0.5)
    white = np.all(with_det == 255, axis=2)
    assert white.sum() > 20
    by_height = draw_bev(sample.points, size_px=300)  # no slices: colour by height
    assert (by_height != blank).any(axis=2).sum() > 1000


def test_bev_rejects_bad_input(sample):
    pts = np.concatenate(split_sweep(sample.points, 8))
    with pytest.raises(ValueError, match="slice_of_point"):
        draw_bev(pts, slice_of_point=pts[:10, 5])
    with pytest.raises(ValueError, match=r"\[0, 4\)"):
        draw_bev(pts, slice_of_point=pts[:, 5], n_slices=4)
    with pytest.raises(ValueError, match="slices"):
        draw_bev(pts, n_slices=3)
    with pytest.raises(ValueError, match="boxes"):
        draw_bev(pts, boxes=np.zeros((2, 7)))
    with pytest.raises(ValueError, match="det_scores"):
        draw_bev(pts, det_boxes=sample.gt_boxes[:3], det_scores=np.ones(2))
    with pytest.raises(ValueError, match="range_m"):
        draw_bev(pts, range_m=0.0)


def test_camera_boxes_are_drawn_where_they_project(sample):
    cam = sample.rig.camera("CAM_FRONT").resized(400, 225)
    image = load_image(sample.image_paths["CAM_FRONT"], size=(400, 225))
    plain = draw_camera_boxes(image, cam, np.zeros((0, 9)))
    drawn = draw_camera_boxes(image, cam, sample.gt_boxes, sample.gt_labels, thickness=1)
    changed = np.any(drawn != plain, axis=2)
    assert changed.sum() > 500
    car = np.flatnonzero(sample.gt_labels == 0)
    visible = cam.visible(sample.gt_boxes[car, :3], min_depth_m=1.0)
    uv, _ = cam.project(sample.gt_boxes[car[visible], :3])
    # every visible car's centre has drawn pixels nearby (its wireframe surrounds it)
    for u, v in uv:
        r0, c0 = int(v), int(u)
        assert changed[max(r0 - 40, 0) : r0 + 40, max(c0 - 60, 0) : c0 + 60].any()
    assert tuple(int(x) for x in drawn[changed][0]) != (0, 0, 0)
    assert len(CLASS_COLORS_BGR) == 10
    with pytest.raises(ValueError, match="400x225"):
        draw_camera_boxes(np.zeros((10, 10, 3), np.uint8), cam, sample.gt_boxes)


def test_mosaic_and_previews(sample, tmp_path):
    tiles = {name: np.full((9, 16, 3), i * 20, np.uint8) for i, name in enumerate(sample.rig.names)}
    mosaic = camera_mosaic(tiles)
    assert mosaic.shape == (18, 48, 3)
    assert mosaic[0, 16, 0] == tiles["CAM_FRONT"][0, 0, 0] and mosaic[9, 16, 0] == tiles["CAM_BACK"][0, 0, 0]
    paths = write_previews(sample, tmp_path, n_slices=8, max_width_px=600)
    assert [p.name for p in paths] == ["scene-0061_ca9a282c_cameras.png", "scene-0061_ca9a282c_bev.png"]
    assert load_image(paths[0]).shape == (225, 600, 3)


def test_cli_writes_a_dataset_and_previews(tmp_path):
    runner = CliRunner()
    out = tmp_path / "ds"
    args = ["--out", str(out), "--scenes", "1", "--samples-per-scene", "1", "--resolution", "64x36", "--seed", "5"]
    result = runner.invoke(main, args + ["--preview"])
    assert result.exit_code == 0, result.output
    assert "wrote 1 scenes, 1 key frames" in result.output
    assert (out / "v1.0-synth" / "sample.json").is_file() and (out / "splits.json").is_file()
    assert len(list((out / "preview").glob("*.png"))) == 2
    again = runner.invoke(main, args)
    assert again.exit_code == 1 and "already exists" in again.output and "Traceback" not in again.output
    assert runner.invoke(main, args + ["--overwrite"]).exit_code == 0


@pytest.mark.parametrize(
    "args,message",
    [
        (["--resolution", "800"], "WIDTHxHEIGHT"),
        (["--resolution", "8x8"], "16..4096"),
        (["--scenes", "0"], "--scenes"),
        (["--sweeps-per-sample", "11"], "--sweeps-per-sample"),
    ],
)
def test_cli_rejects_bad_options(tmp_path, args, message):
    result = CliRunner().invoke(main, ["--out", str(tmp_path / "x")] + args)
    assert result.exit_code == 2 and message in result.output and "Traceback" not in result.output


def test_cli_rejects_a_file_as_out(tmp_path):
    f = tmp_path / "file"
    f.write_text("x")
    result = CliRunner().invoke(main, ["--out", str(f)])
    assert result.exit_code != 0 and "Traceback" not in result.output


def test_one_palette_for_pictures_and_markers():
    """The preview's BGR colours are core.classes' RGB ones reversed: a class is one colour everywhere."""
    from streamdet.core.classes import CLASS_COLORS_RGB, NUM_CLASSES, OTHER_COLOR_RGB, class_color_rgb

    assert len(CLASS_COLORS_RGB) == NUM_CLASSES and len(set(CLASS_COLORS_RGB)) == NUM_CLASSES
    assert OTHER_COLOR_RGB not in CLASS_COLORS_RGB
    assert [c[::-1] for c in CLASS_COLORS_BGR] == list(CLASS_COLORS_RGB)
    assert [class_color_rgb(k) for k in range(NUM_CLASSES)] == list(CLASS_COLORS_RGB)
    assert class_color_rgb(-1) == class_color_rgb(NUM_CLASSES) == OTHER_COLOR_RGB
