"""GIFs of closed-loop runs: the drivable area, the log's lanes, the agents, the ego (red) with its driven path and
its open-loop plan (dashed), at 5 frames per second of the stored rate. A legend under the scene names each of
these (the agents as the log's, IDM's or the model's), a scale bar in metres sits in the lower right corner and the
title carries each frame's time. Matplotlib's Agg canvas and Pillow only."""

from __future__ import annotations

import os
import re

import numpy as np

from gpd_jax.plotting import Picture, add_scale_bar, legend_band

EGO, AGENT = "#d62728", "#1f77b4"
AREA, EDGE, LANE = "#e6e6e6", "#888888", "#bbbbbb"
# who moves the other agents of a run (`gpd_jax.sim.run(..., agents=)`): the legend's words for them
AGENT_LABELS = {"log": "agents (log replay)", "idm": "agents (IDM)", "gpd": "agents (model)"}


def _boxes(xy, heading, size):
    c, s = np.cos(heading), np.sin(heading)
    fwd = np.stack([c, s], -1) * size[:, :1] / 2
    left = np.stack([-s, c], -1) * size[:, 1:2] / 2
    signs = np.array([[1, 1], [-1, 1], [-1, -1], [1, -1]], np.float64)
    return xy[:, None] + signs[None, :, :1] * fwd[:, None] + signs[None, :, 1:] * left[:, None]


def _agent_mode(agents: str | None, title: str) -> str | None:
    """The run's agent model: `agents`, else the "<mode> agents" words of the title (how gpd_jax.plan titles)."""
    if agents is not None:
        return agents
    m = re.search(r"\b(log|idm|gpd) agents\b", title)
    return m.group(1) if m else None


def run_figure(*, fine_xy, fine_heading, fine_valid, size, road=None, polylines=None, polyline_valid=None,
               plan=None, start: int = 0, title: str = "", size_px: int = 360, view_m: float = 45.0,
               agents: str | None = None) -> Picture:
    """The figure of `render_run` (same arguments less the path and `every`), not yet drawn. `agents`: who moves
    the other agents ("log", "idm", "gpd"; default: read from the title's "<mode> agents", else unnamed)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch, Polygon

    fig = Figure(figsize=(size_px / 100, size_px / 100), dpi=100)
    FigureCanvasAgg(fig)
    top = 0.93
    ax = fig.add_axes((0, 0, 1, top))
    ax.set_aspect("equal")
    ax.set_xticks([])
    ax.set_yticks([])
    if road is not None:
        for ring, ok in zip(np.asarray(road.polygons), np.asarray(road.polygon_valid)):
            if ok.sum() >= 3:
                ax.add_patch(Polygon(ring[ok], closed=True, facecolor=AREA, edgecolor="none", zorder=0))
        for e, ok in zip(np.asarray(road.edges), np.asarray(road.edge_valid)):
            if ok.sum() >= 2:
                ax.plot(e[ok, 0], e[ok, 1], color=EDGE, lw=0.8, zorder=1)
    if polylines is not None:
        for ln, ok in zip(np.asarray(polylines), np.asarray(polyline_valid)):
            if ok.sum() >= 2:
                ax.plot(ln[ok, 0], ln[ok, 1], color=LANE, lw=0.5, ls=":", zorder=1)
    xy, hd, vd = np.asarray(fine_xy), np.asarray(fine_heading), np.asarray(fine_valid)
    size = np.asarray(size)
    ax.plot(xy[start:, 0, 0], xy[start:, 0, 1], color=EGO, lw=1.2, alpha=0.6, zorder=2)
    if plan is not None:
        p = np.asarray(plan)
        ax.plot(np.r_[xy[start, 0, 0], p[:, 0]], np.r_[xy[start, 0, 1], p[:, 1]], color=EGO, lw=1.0, ls="--",
                zorder=2)

    box = lambda color: Patch(facecolor=color, edgecolor="none", alpha=0.85)
    entries = [(box(EGO), "ego (planner)")]
    if xy.shape[1] > 1:
        entries.append((box(AGENT), AGENT_LABELS.get(_agent_mode(agents, title), "other agents")))
    entries.append((Line2D([], [], color=EGO, lw=1.2, alpha=0.6), "ego's driven path"))
    if plan is not None:
        entries.append((Line2D([], [], color=EGO, lw=1.0, ls="--"), "ego's plan"))
    if road is not None:
        entries += [(Patch(facecolor=AREA, edgecolor="none"), "drivable area"),
                    (Line2D([], [], color=EDGE, lw=0.8), "road edges")]
    if polylines is not None:
        entries.append((Line2D([], [], color="#999999", lw=0.8, ls=":"), "log's lanes"))
    labels = tuple(e[1] for e in entries)
    legend = legend_band(fig, ax, [e[0] for e in entries], list(labels), 6, top)
    scale_bar = add_scale_bar(ax, view_m, 6)

    patches = []

    def draw(t: int) -> np.ndarray:
        for pa in patches:
            pa.remove()
        patches.clear()
        corners = _boxes(xy[t], hd[t], size)
        for a in np.nonzero(vd[t])[0]:
            pa = Polygon(corners[a], closed=True, facecolor=EGO if a == 0 else AGENT, alpha=0.85, zorder=3)
            ax.add_patch(pa)
            patches.append(pa)
        cx, cy = xy[t, 0]
        ax.set_xlim(cx - view_m, cx + view_m)
        ax.set_ylim(cy - view_m, cy + view_m)
        fig.suptitle(f"{title}  t={0.1 * (t - start):.1f} s", fontsize=8)
        fig.canvas.draw()
        return np.asarray(fig.canvas.buffer_rgba())[..., :3].copy()

    return Picture(fig, ax, legend, scale_bar, labels, draw)


def render_run(path: str, *, fine_xy, fine_heading, fine_valid, size, road=None, polylines=None,
               polyline_valid=None, plan=None, start: int = 0, every: int = 2, title: str = "",
               size_px: int = 360, view_m: float = 45.0) -> str:
    """Writes one GIF. fine_* [Ts, A, ...] one run at the stored rate, size f32[A, 2], road a RoadGeometry of one
    scene (numpy leaves) or None, polylines f32[L, P, 2] / bool[L, P], plan f32[F, 3] or None; frames from `start`
    every `every` stored frames. The legend names the agents by the title's "<mode> agents" (log, idm, gpd).
    Returns the path."""
    from PIL import Image

    fig = run_figure(fine_xy=fine_xy, fine_heading=fine_heading, fine_valid=fine_valid, size=size, road=road,
                     polylines=polylines, polyline_valid=polyline_valid, plan=plan, start=start, title=title,
                     size_px=size_px, view_m=view_m)
    images = [Image.fromarray(fig.draw(t)) for t in range(start, np.shape(fine_xy)[0], every)]
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    tmp = path + ".tmp.gif"
    images[0].save(tmp, save_all=True, append_images=images[1:], duration=200, loop=0)
    os.replace(tmp, path)
    return path
