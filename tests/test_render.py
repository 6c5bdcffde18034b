"""Rendering: frame transforms, box corners, one GIF + one PNG strip per scenario x task."""

import os

import numpy as np
import pytest
from PIL import Image

from gpd_jax.evaluation import RenderItem
from gpd_jax.evaluation.render import box_polygons, lanes_to_scene, render_items, render_rollout
from gpd_jax.tasks import TASK_NAMES


def test_lanes_to_scene_applies_the_frame_pose():
    pts = np.array([[[1.0, 0.0], [0.0, 2.0]]])  # [L=1, P=2, 2] in the frame's ego frame
    np.testing.assert_allclose(lanes_to_scene(pts, np.array([0.0, 0.0, 0.0])), pts)
    out = lanes_to_scene(pts, np.array([10.0, 5.0, np.pi / 2]))  # ego at (10, 5) facing +y
    np.testing.assert_allclose(out, [[[10.0, 6.0], [8.0, 5.0]]], atol=1e-12)
    # batched over frames
    out = lanes_to_scene(np.stack([pts, pts]), np.array([[0.0, 0.0, 0.0], [1.0, 1.0, np.pi]]))
    np.testing.assert_allclose(out[1], [[[0.0, 1.0], [1.0, -1.0]]], atol=1e-12)


def test_box_polygons():
    c = box_polygons(np.array([[1.0, 2.0]]), np.array([np.pi / 2]), np.array([[4.0, 2.0]]))
    # heading +y: the front edge is at y = 4, the left side at x = 0
    np.testing.assert_allclose(c[0], [[0.0, 4.0], [0.0, 0.0], [2.0, 0.0], [2.0, 4.0]], atol=1e-12)


def _scene(t=7, a=3):
    tt = np.arange(t, dtype=np.float64)[:, None]
    xy = np.stack([5.0 * tt + np.array([0.0, 8.0, -6.0]), np.broadcast_to([0.0, 3.5, -3.5], (t, a))], -1)
    heading = np.zeros((t, a))
    valid = np.ones((t, a), bool)
    valid[:2, 2] = False
    lanes = np.zeros((t, 50, 20, 2), np.float32)
    lanes[:, :3, :, 0] = np.linspace(-30, 30, 20)
    lanes[:, :3, :, 1] = np.array([-3.5, 0.0, 3.5])[:, None]
    ok = np.zeros((t, 50), bool)
    ok[:, :3] = True
    return xy, heading, valid, lanes, ok


def test_render_rollout_writes_gif_and_strip(tmp_path):
    xy, heading, valid, lanes, ok = _scene()
    pred = xy + np.array([0.0, 0.5])
    gif, png = render_rollout(str(tmp_path / "s0_task"), pred_xy=pred, pred_heading=heading, pred_valid=valid,
                              log_xy=xy, log_heading=heading, log_valid=valid, size=np.array([[4.5, 1.9]] * 3),
                              num_history=3, frame_period_s=0.5, title="test", generated=("agent", "map"),
                              lanes=lanes, lanes_valid=ok, log_lanes=lanes, log_lanes_valid=ok, size_px=96,
                              panels=4)
    assert gif.endswith(".gif") and png.endswith(".png")
    with Image.open(gif) as im:
        assert im.size == (96, 96) and im.n_frames == 7
    with Image.open(png) as im:
        # frames 2 (current), 3 or 4, 5, 6 -> 4 panels of 96 px and 3 separators of 3 px
        assert im.size == (4 * 96 + 3 * 3, 96)
        assert np.asarray(im.convert("L")).min() < 128  # something dark was drawn


def test_render_items_one_gif_and_png_per_task(tmp_path):
    xy, heading, valid, _, _ = _scene(t=5)
    k = len(TASK_NAMES)
    rep = lambda x: np.repeat(x[None], k, 0)
    item = RenderItem(index=3, scenario_id="x/1",
                      pred={"xy": rep(xy), "heading": rep(heading), "valid": rep(valid),
                            "map_tokens": np.zeros((k, 5, 64), np.int32)},
                      log={"xy": xy, "heading": heading, "valid": valid, "size": np.full((3, 2), 2.0),
                           "agent_type": np.zeros(3, np.int32), "map_tokens": np.zeros((5, 64), np.int32),
                           "ego_pose": np.concatenate([xy[:, 0], heading[:, :1]], -1)})
    paths = render_items([item], TASK_NAMES, str(tmp_path / "render"), num_history=2, frame_period_s=1.0,
                         tokenizer=None, size_px=64, panels=3)
    names = sorted(os.listdir(tmp_path / "render"))
    assert names == sorted(f"0003_{t}.{e}" for t in TASK_NAMES for e in ("gif", "png"))
    assert len(paths) == 2 * k


@pytest.mark.parametrize("panels", [1, 2])
def test_strip_with_few_panels(tmp_path, panels):
    xy, heading, valid, _, _ = _scene(t=4)
    _, png = render_rollout(str(tmp_path / "a"), pred_xy=xy, pred_heading=heading, pred_valid=valid, log_xy=xy,
                            log_heading=heading, log_valid=valid, size=np.full((3, 2), 3.0), num_history=2,
                            frame_period_s=0.1, size_px=48, panels=panels)
    with Image.open(png) as im:
        assert im.size == (panels * 48 + (panels - 1) * 3, 48)
