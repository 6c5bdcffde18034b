"""Pictures of rollouts like the paper's figures: an animated GIF and a PNG strip per scenario and task.

Bird's-eye view in the scene frame (the ego frame of the current frame), the camera following the rolled-out
ego. Drawn per frame:

* lanes decoded from the frame's map tokens (the task's: predicted where the task generates the map, logged
  otherwise); a frame's lanes are in that frame's ego frame: logged tokens are placed with the logged ego pose,
  generated ones with the rolled-out ego pose of the frame (the model generates the map around its own ego).
  Where the map is generated, the lanes of the logged tokens are drawn faint underneath;
* the rolled-out ego (red) and agents (blue) as oriented boxes with a heading tick (slots the task takes from
  the log in pale colours), their rolled-out paths from the current frame on as solid lines;
* the log: every logged path as a faint line and the logged boxes of the frame as dashed ghosts;
* a legend under the scene (from 240 px on) naming each of these as the model's, the log's or the prompt's, a
  scale bar in metres (lower right) and the time of the frame (title: seconds from the current frame).

Only matplotlib (Agg canvas, no pyplot state) and Pillow. One figure per scenario x task is drawn once and its
artists are updated frame by frame, which keeps a 21-frame scenario x task near a second.
"""

from __future__ import annotations

import os
from collections.abc import Sequence

import numpy as np

from gpd_jax.plotting import Picture, add_scale_bar, legend_band
from gpd_jax.tasks import generated

EGO, AGENT = "#d62728", "#1f77b4"
EGO_GIVEN, AGENT_GIVEN = "#f0a8a8", "#a9c4de"
LANE, LANE_LOG = "#555555", "#c8c8c8"
GIVEN_LANE = "#2ca02c"  # a prompt's own lanes (drawn under everything, wide and pale green)


def lanes_to_scene(points: np.ndarray, poses: np.ndarray) -> np.ndarray:
    """Lines in each frame's ego frame -> scene frame. points f32[..., L, P, 2], poses f32[..., 3] (x, y, heading)."""
    c, s = np.cos(poses[..., 2]), np.sin(poses[..., 2])
    c, s = c[..., None, None], s[..., None, None]
    x, y = points[..., 0], points[..., 1]
    return np.stack([c * x - s * y + poses[..., None, None, 0], s * x + c * y + poses[..., None, None, 1]], -1)


def box_polygons(xy: np.ndarray, heading: np.ndarray, size: np.ndarray) -> np.ndarray:
    """Oriented box corners f32[N, 4, 2] of centres xy f32[N, 2], heading f32[N], size f32[N, 2] (length, width)."""
    c, s = np.cos(heading), np.sin(heading)
    fwd = np.stack([c, s], -1) * size[:, :1] / 2
    left = np.stack([-s, c], -1) * size[:, 1:2] / 2
    signs = np.array([[1, 1], [-1, 1], [-1, -1], [1, -1]], np.float64)
    return xy[:, None, :] + signs[None, :, :1] * fwd[:, None, :] + signs[None, :, 1:] * left[:, None, :]


def _runs(xy: np.ndarray, valid: np.ndarray) -> list[np.ndarray]:
    """Polylines of the consecutive valid frames of one slot: xy [T, 2], valid [T]."""
    out, start = [], None
    for t, v in enumerate(list(valid) + [False]):
        if v and start is None:
            start = t
        elif not v and start is not None:
            if t - start >= 2:
                out.append(xy[start:t])
            start = None
    return out


def rollout_figure(*, pred_xy, pred_heading, pred_valid, log_xy, log_heading, log_valid, size, num_history: int,
                   frame_period_s: float, title: str = "", generated: Sequence[str] = ("ego", "agent", "map"),
                   lanes=None, lanes_valid=None, lane_poses=None, log_lanes=None, log_lanes_valid=None,
                   size_px: int = 320, view_m: float = 40.0, given=None, given_lanes=None,
                   given_lanes_valid=None) -> Picture:
    """The figure of `render_rollout` (same arguments, less the output's stem and panels), not yet drawn.

    The legend (at `size_px` >= 240, in a band under the scene) names what is drawn: the ego's and the agents'
    boxes as the model's or the log's (by `generated`, or `given` where a prompt gives slots), the logged boxes and
    paths, the model's paths, and the lanes: the model's (decoded from its generated map tokens), the log's, the
    prompt's own. A scale bar in metres sits in the lower right corner; the title carries each frame's time.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.collections import LineCollection, PolyCollection
    from matplotlib.figure import Figure
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch

    pxy, phd, pv = (np.asarray(a, np.float64) if i < 2 else np.asarray(a, bool)
                    for i, a in enumerate((pred_xy, pred_heading, pred_valid)))
    lxy, lhd, lv = (np.asarray(a, np.float64) if i < 2 else np.asarray(a, bool)
                    for i, a in enumerate((log_xy, log_heading, log_valid)))
    size = np.asarray(size, np.float64)
    t_total, a = pv.shape
    cur = num_history - 1
    slot_colors = np.array([EGO if "ego" in generated else EGO_GIVEN] +
                           [AGENT if "agent" in generated else AGENT_GIVEN] * (a - 1), dtype=object)
    ego_pose = np.concatenate([pxy[:, 0], phd[:, :1]], -1)
    lane_sc = None
    if lanes is not None:
        lane_sc = lanes_to_scene(np.asarray(lanes, np.float64), ego_pose if lane_poses is None
                                 else np.asarray(lane_poses, np.float64))
    log_lane_sc = None
    if log_lanes is not None:
        log_pose = np.concatenate([lxy[:, 0], lhd[:, :1]], -1)
        log_lane_sc = lanes_to_scene(np.asarray(log_lanes, np.float64), log_pose)

    dpi = 100
    fig = Figure(figsize=(size_px / dpi, size_px / dpi), dpi=dpi, facecolor="white")
    canvas = FigureCanvasAgg(fig)
    with_legend = size_px >= 240
    top = 0.9
    ax = fig.add_axes((0.0, 0.0, 1.0, top))
    ax.set_aspect("equal")
    ax.set_axis_off()
    if given_lanes is not None:
        gl, gv = np.asarray(given_lanes, np.float64), np.asarray(given_lanes_valid, bool)
        ax.add_collection(LineCollection([ln[ok] for ln, ok in zip(gl, gv) if ok.sum() >= 2], colors=GIVEN_LANE,
                                         linewidths=6.0, alpha=0.25, zorder=0))
    given_mask = None if given is None else np.asarray(given, bool)
    log_lane_lc = ax.add_collection(LineCollection([], colors=LANE_LOG, linewidths=0.8, zorder=1))
    lane_lc = ax.add_collection(LineCollection([], colors=LANE, linewidths=0.8, zorder=2))
    # static: logged paths
    segs, cols = [], []
    for j in range(a):
        for r in _runs(lxy[:, j], lv[:, j]):
            segs.append(r)
            cols.append(EGO if j == 0 else AGENT)
    ax.add_collection(LineCollection(segs, colors=cols, linewidths=1.0, alpha=0.25, zorder=3))
    path_lc = ax.add_collection(LineCollection([], linewidths=1.3, zorder=4))
    ghost_pc = ax.add_collection(PolyCollection([], facecolors="none", edgecolors="#333333", linewidths=0.7,
                                                linestyles="--", alpha=0.6, zorder=5))
    box_pc = ax.add_collection(PolyCollection([], edgecolors="black", linewidths=0.5, alpha=0.9, zorder=6))
    tick_lc = ax.add_collection(LineCollection([], colors="black", linewidths=0.8, zorder=7))
    fs = max(5, size_px // 45)
    head = fig.text(0.02, 0.95, "", fontsize=fs, va="center", ha="left")

    # the legend: what each colour and line style means, only for what this picture draws
    box = lambda color, edge="black": Patch(facecolor=color, edgecolor=edge, linewidth=0.6)
    entries = []
    if given_mask is not None:
        entries.append((box(EGO), "ego (model)"))
        if a > 1:
            entries.append((box(AGENT), "agents (model)"))
        if given_mask.any():
            entries.append((box(AGENT_GIVEN, GIVEN_LANE), "given by the prompt"))
    else:
        entries.append((box(slot_colors[0]), "ego (model)" if "ego" in generated else "ego (log)"))
        if a > 1:
            entries.append((box(slot_colors[1]), "agents (model)" if "agent" in generated else "agents (log)"))
    entries.append((Patch(facecolor="none", edgecolor="#333333", linestyle="--", linewidth=0.7), "logged boxes"))
    entries.append((Line2D([], [], color=AGENT, lw=1.3), "model's paths"))
    entries.append((Line2D([], [], color=AGENT, lw=1.0, alpha=0.25), "logged paths"))
    if lanes is not None:
        entries.append((Line2D([], [], color=LANE, lw=0.8), "model's lanes" if "map" in generated else "log's lanes"))
    if log_lanes is not None:
        entries.append((Line2D([], [], color=LANE_LOG, lw=0.8), "log's lanes"))
    if given_lanes is not None:
        entries.append((Line2D([], [], color=GIVEN_LANE, lw=5.0, alpha=0.25), "prompt's lanes"))
    handles, labels = [e[0] for e in entries], tuple(e[1] for e in entries)
    legend = legend_band(fig, ax, handles, list(labels), max(5, fs - 1), top) if with_legend else None
    scale_bar = add_scale_bar(ax, view_m, max(4, fs - 1))

    def draw(t: int) -> np.ndarray:
        if lane_sc is not None:
            ok = np.asarray(lanes_valid[t], bool)
            lane_lc.set_segments(list(lane_sc[t][ok]))
        if log_lane_sc is not None:
            ok = np.asarray(log_lanes_valid[t], bool)
            log_lane_lc.set_segments(list(log_lane_sc[t][ok]))
        g = lv[t]
        ghost_pc.set_verts(list(box_polygons(lxy[t][g], lhd[t][g], size[g])))
        v = pv[t]
        boxes = box_polygons(pxy[t][v], phd[t][v], size[v])
        box_pc.set_verts(list(boxes))
        colors = slot_colors
        if given_mask is not None:
            colors = np.where(given_mask[t], np.array([EGO_GIVEN] + [AGENT_GIVEN] * (a - 1), dtype=object),
                              np.array([EGO] + [AGENT] * (a - 1), dtype=object))
        box_pc.set_facecolor(list(colors[v]))
        if given_mask is not None:
            box_pc.set_edgecolor(list(np.where(given_mask[t][v], GIVEN_LANE, "black")))
        front = boxes[:, [0, 3]].mean(1)
        tick_lc.set_segments([np.stack([c, f]) for c, f in zip(pxy[t][v], front)])
        psegs, pcols = [], []
        if t > cur:
            for j in range(a):
                for r in _runs(pxy[cur:t + 1, j], pv[cur:t + 1, j]):
                    psegs.append(r)
                    pcols.append(slot_colors[j])
        path_lc.set_segments(psegs)
        path_lc.set_color(pcols if pcols else "black")
        c = pxy[t, 0] if pv[t, 0] else lxy[t, 0]
        ax.set_xlim(c[0] - view_m, c[0] + view_m)
        ax.set_ylim(c[1] - view_m, c[1] + view_m)
        secs = (t - cur) * frame_period_s
        head.set_text(f"{title}  t={secs:+.1f} s" + ("  (history)" if t <= cur else ""))
        canvas.draw()
        return np.asarray(canvas.buffer_rgba())[..., :3].copy()

    return Picture(fig, ax, legend, scale_bar, labels, draw)


def render_rollout(stem: str, *, pred_xy, pred_heading, pred_valid, log_xy, log_heading, log_valid, size,
                   num_history: int, frame_period_s: float, title: str = "",
                   generated: Sequence[str] = ("ego", "agent", "map"), lanes=None, lanes_valid=None,
                   lane_poses=None, log_lanes=None, log_lanes_valid=None, size_px: int = 320, panels: int = 4,
                   view_m: float = 40.0, given=None, given_lanes=None, given_lanes_valid=None) -> tuple[str, str]:
    """Writes `stem.gif` (every frame) and `stem.png` (a strip of `panels` frames from the current one on).

    Args:
      pred_*: the rolled-out scene f32[T, A, 2], f32[T, A], bool[T, A] (history frames are the log's).
      log_*: the logged scene, same shapes; size: f32[A, 2] (length, width).
      num_history: H; frame H - 1 is the current frame. frame_period_s: seconds between frames.
      generated: what the task generates ("ego", "agent", "map"): given slots are drawn pale.
      lanes, lanes_valid: optional f32[T, L, P, 2] lines in each frame's ego frame and bool[T, L]; lane_poses:
        f32[T, 3] the pose of each frame's ego frame in the scene frame (default: the rolled-out ego).
      log_lanes, log_lanes_valid: optional faint reference lines (same layout, placed with the log's ego pose).
      size_px: side of one frame in pixels (a legend under the scene from 240 px on); view_m: half side of the
        view in metres (a scale bar of 1, 2 or 5 x 10^k m fitting a quarter of it).
      given: optional bool[T, A] a prompt's per-frame given slots (drawn pale with a green edge, overriding
        `generated` for agents); given_lanes, given_lanes_valid: optional f32[L, P, 2] / bool[L, P] a prompt's
        own lanes in the scene frame (wide pale green underneath).

    Returns:
      (gif path, png path).
    """
    from PIL import Image

    t_total = np.shape(pred_valid)[0]
    cur = num_history - 1
    fig = rollout_figure(pred_xy=pred_xy, pred_heading=pred_heading, pred_valid=pred_valid, log_xy=log_xy,
                         log_heading=log_heading, log_valid=log_valid, size=size, num_history=num_history,
                         frame_period_s=frame_period_s, title=title, generated=generated, lanes=lanes,
                         lanes_valid=lanes_valid, lane_poses=lane_poses, log_lanes=log_lanes,
                         log_lanes_valid=log_lanes_valid, size_px=size_px, view_m=view_m, given=given,
                         given_lanes=given_lanes, given_lanes_valid=given_lanes_valid)
    frames = [fig.draw(t) for t in range(t_total)]
    os.makedirs(os.path.dirname(os.path.abspath(stem)), exist_ok=True)
    gif, png = stem + ".gif", stem + ".png"
    imgs = [Image.fromarray(f).convert("P", palette=Image.Palette.ADAPTIVE, colors=64) for f in frames]
    imgs[0].save(gif, save_all=True, append_images=imgs[1:], duration=max(20, int(round(frame_period_s * 1000))),
                 loop=0)
    picks = np.unique(np.round(np.linspace(cur, t_total - 1, max(1, panels))).astype(int))
    sep = np.full((frames[0].shape[0], 3, 3), 255, np.uint8)
    strip = np.concatenate(sum([[frames[t], sep] for t in picks], [])[:-1], axis=1)
    Image.fromarray(strip).save(png, optimize=True)
    return gif, png


def render_items(items, task_names: Sequence[str], out_dir: str, *, num_history: int, frame_period_s: float,
                 tokenizer=None, size_px: int = 320, panels: int = 4, progress: bool = False) -> list[str]:
    """Renders every task of every `gpd_jax.evaluation.RenderItem` into `out_dir` as
    `<scenario index>_<task>.gif` / `.png`. Lanes are decoded with `tokenizer` (none drawn without one).

    Returns the written paths.
    """

    paths: list[str] = []
    for it in items:
        lanes = lanes_ok = None
        if tokenizer is not None:
            toks = np.concatenate([it.pred["map_tokens"], it.log["map_tokens"][None]], 0)  # [K + 1, T, M]
            pts, logits = tokenizer.decode_tokens(toks)
            lanes, lanes_ok = np.asarray(pts), np.asarray(logits) > 0
        for k, name in enumerate(task_names):
            gen = generated(name)
            kw = {}
            if lanes is not None:
                kw = dict(lanes=lanes[k], lanes_valid=lanes_ok[k])
                if "map" in gen:
                    kw.update(log_lanes=lanes[-1], log_lanes_valid=lanes_ok[-1])
                else:  # logged map tokens are in the logged ego's frames
                    kw.update(lane_poses=it.log["ego_pose"])
            stem = os.path.join(out_dir, f"{it.index:04d}_{name}")
            title = f"#{it.index} {name.replace('_', ' ')}"
            paths += list(render_rollout(
                stem, pred_xy=it.pred["xy"][k], pred_heading=it.pred["heading"][k], pred_valid=it.pred["valid"][k],
                log_xy=it.log["xy"], log_heading=it.log["heading"], log_valid=it.log["valid"], size=it.log["size"],
                num_history=num_history, frame_period_s=frame_period_s, title=title, generated=gen,
                size_px=size_px, panels=panels, **kw))
            if progress:
                print(f"rendered {stem}.gif/.png", flush=True)
    return paths
