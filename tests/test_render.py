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


def _legend_texts(fig) -> list[str]:
    return [t.get_text() for leg in fig.fig.legends for t in leg.get_texts()]


def _below_scene(fig) -> bool:
    """The legend's box lies under the scene's axes (it covers nothing drawn)."""
    renderer = fig.fig.canvas.get_renderer()
    leg = fig.legend.get_window_extent(renderer)
    return leg.y1 <= fig.ax.get_window_extent(renderer).y0 + 1


def _rollout_fig(**kw):
    from gpd_jax.evaluation.render import rollout_figure

    xy, heading, valid, lanes, ok = _scene()
    args = dict(pred_xy=xy + np.array([0.0, 0.5]), pred_heading=heading, pred_valid=valid, log_xy=xy,
                log_heading=heading, log_valid=valid, size=np.array([[4.5, 1.9]] * 3), num_history=3,
                frame_period_s=0.5, title="test", lanes=lanes, lanes_valid=ok, size_px=320)
    return rollout_figure(**{**args, **kw})


def test_rollout_figure_has_a_legend_a_scale_bar_and_the_frame_time():
    """A reader learns from the picture itself which boxes and lanes are the model's and which the log's, how
    long 20 m is and the time of each frame; the legend sits under the scene, not on it."""
    _, _, _, lanes, ok = _scene()
    fig = _rollout_fig(generated=("ego", "agent", "map"), log_lanes=lanes, log_lanes_valid=ok)
    assert fig.legend is not None and fig.legend in fig.fig.legends
    texts = _legend_texts(fig)
    assert texts == list(fig.labels)
    for label in ("ego (model)", "agents (model)", "logged boxes", "model's paths", "logged paths",
                  "model's lanes", "log's lanes"):
        assert label in texts, (label, texts)
    assert fig.scale_bar in fig.ax.get_children() and fig.scale_bar.txt_label.get_text() == "20 m"
    img = fig.draw(5)
    assert img.shape == (320, 320, 3)
    assert _below_scene(fig)
    title = [t.get_text() for t in fig.fig.texts if "t=" in t.get_text()]
    assert title and "t=+1.5 s" in title[0]  # (5 - 2) frames of 0.5 s after the current one


def test_rollout_legend_names_what_each_task_and_prompt_takes_from_elsewhere():
    fig = _rollout_fig(generated=("agent",))  # closed loop: the ego and the map are the log's
    texts = _legend_texts(fig)
    assert "ego (log)" in texts and "agents (model)" in texts and "log's lanes" in texts
    assert "ego (model)" not in texts and "model's lanes" not in texts
    fig = _rollout_fig(generated=("ego",), lanes=None, lanes_valid=None)  # motion planning, no lanes drawn
    texts = _legend_texts(fig)
    assert "agents (log)" in texts and not any("lanes" in t for t in texts)
    given = np.zeros((7, 3), bool)
    given[:, 1] = True
    gl = np.zeros((1, 5, 2))
    gl[0, :, 0] = np.arange(5.0)
    fig = _rollout_fig(given=given, given_lanes=gl, given_lanes_valid=np.ones((1, 5), bool))
    texts = _legend_texts(fig)
    assert {"ego (model)", "agents (model)", "given by the prompt", "model's lanes", "prompt's lanes"} <= set(texts)
    # small thumbnails keep the scale bar but have no room for a legend
    fig = _rollout_fig(size_px=96)
    assert fig.legend is None and fig.scale_bar.txt_label.get_text() == "20 m"


def test_scale_bar_length_fits_the_view():
    from gpd_jax.plotting import scale_bar_m

    assert [scale_bar_m(v) for v in (5.0, 10.0, 40.0, 45.0, 50.0, 100.0, 300.0)] == [2, 5, 20, 20, 20, 50, 100]
    for v in (3.0, 17.0, 45.0, 640.0):
        assert scale_bar_m(v) <= 0.5 * v


def _sim_run(t=30, a=3):
    from types import SimpleNamespace

    tt = np.arange(t, dtype=np.float64)[:, None] * 0.1
    xy = np.stack([8.0 * tt + np.array([0.0, 12.0, -10.0]), np.broadcast_to([-1.75, 1.75, -1.75], (t, a))], -1)
    ring = np.array([[[-50.0, -3.5], [100.0, -3.5], [100.0, 3.5], [-50.0, 3.5]]])
    edges = np.array([[[-50.0, -3.5], [100.0, -3.5]], [[-50.0, 3.5], [100.0, 3.5]]])
    road = SimpleNamespace(polygons=ring, polygon_valid=np.ones((1, 4), bool), edges=edges,
                           edge_valid=np.ones((2, 2), bool))
    plan = np.stack([np.linspace(1.0, 30.0, 8), np.full(8, -1.75), np.zeros(8)], -1)
    return dict(fine_xy=xy, fine_heading=np.zeros((t, a)), fine_valid=np.ones((t, a), bool),
                size=np.full((a, 2), 3.0), road=road, polylines=edges * 0.5, polyline_valid=np.ones((2, 2), bool),
                plan=plan, start=9)


def test_closed_loop_figure_has_a_legend_and_a_scale_bar():
    from gpd_jax.sim.render import run_figure

    fig = run_figure(**_sim_run(), title="constant_velocity / idm agents #0")
    texts = _legend_texts(fig)
    assert texts == list(fig.labels)
    for label in ("ego (planner)", "agents (IDM)", "ego's driven path", "ego's plan", "drivable area", "road edges",
                  "log's lanes"):
        assert label in texts, (label, texts)
    assert fig.scale_bar in fig.ax.get_children() and fig.scale_bar.txt_label.get_text() == "20 m"
    assert fig.draw(19).shape == (360, 360, 3) and _below_scene(fig)
    assert "t=1.0 s" in fig.fig._suptitle.get_text()
    for mode, label in (("log", "agents (log replay)"), ("gpd", "agents (model)")):
        assert label in _legend_texts(run_figure(**_sim_run(), title=f"p / {mode} agents #1"))
    assert "agents (model)" in _legend_texts(run_figure(**_sim_run(), title="a run", agents="gpd"))


def test_render_run_writes_a_gif(tmp_path):
    from gpd_jax.sim.render import render_run

    path = render_run(str(tmp_path / "run.gif"), **_sim_run(), every=5, title="p / log agents #0", size_px=200)
    with Image.open(path) as im:
        assert im.size == (200, 200) and im.n_frames == 5  # stored frames 9, 14, ..., 29
