"""GIFs of closed-loop runs: the drivable area, the log's lanes, the agents, the ego (red) with its driven path and
its open-loop plan (dashed), at 5 frames per second of the stored rate. Matplotlib's Agg canvas and Pillow only."""

from __future__ import annotations

import os

import numpy as np


def _boxes(xy, heading, size):
    c, s = np.cos(heading), np.sin(heading)
    fwd = np.stack([c, s], -1) * size[:, :1] / 2
    left = np.stack([-s, c], -1) * size[:, 1:2] / 2
    signs = np.array([[1, 1], [-1, 1], [-1, -1], [1, -1]], np.float64)
    return xy[:, None] + signs[None, :, :1] * fwd[:, None] + signs[None, :, 1:] * left[:, None]


def render_run(path: str, *, fine_xy, fine_heading, fine_valid, size, road=None, polylines=None,
               polyline_valid=None, plan=None, start: int = 0, every: int = 2, title: str = "",
               size_px: int = 360, view_m: float = 45.0) -> str:
    """Writes one GIF. fine_* [Ts, A, ...] one run at the stored rate, size f32[A, 2], road a RoadGeometry of one
    scene (numpy leaves) or None, polylines f32[L, P, 2] / bool[L, P], plan f32[F, 3] or None; frames from `start`
    every `every` stored frames. Returns the path."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from matplotlib.patches import Polygon
    from PIL import Image

    fig = Figure(figsize=(size_px / 100, size_px / 100), dpi=100)
    FigureCanvasAgg(fig)
    ax = fig.add_axes((0, 0, 1, 0.93))
    ax.set_aspect("equal")
    ax.set_xticks([])
    ax.set_yticks([])
    if road is not None:
        for ring, ok in zip(np.asarray(road.polygons), np.asarray(road.polygon_valid)):
            if ok.sum() >= 3:
                ax.add_patch(Polygon(ring[ok], closed=True, facecolor="#e6e6e6", edgecolor="none", zorder=0))
        for e, ok in zip(np.asarray(road.edges), np.asarray(road.edge_valid)):
            if ok.sum() >= 2:
                ax.plot(e[ok, 0], e[ok, 1], color="#888888", lw=0.8, zorder=1)
    if polylines is not None:
        for ln, ok in zip(np.asarray(polylines), np.asarray(polyline_valid)):
            if ok.sum() >= 2:
                ax.plot(ln[ok, 0], ln[ok, 1], color="#bbbbbb", lw=0.5, ls=":", zorder=1)
    xy, hd, vd = np.asarray(fine_xy), np.asarray(fine_heading), np.asarray(fine_valid)
    size = np.asarray(size)
    ax.plot(xy[start:, 0, 0], xy[start:, 0, 1], color="#d62728", lw=1.2, alpha=0.6, zorder=2)
    if plan is not None:
        p = np.asarray(plan)
        ax.plot(np.r_[xy[start, 0, 0], p[:, 0]], np.r_[xy[start, 0, 1], p[:, 1]], color="#d62728", lw=1.0, ls="--",
                zorder=2)
    patches = []
    images = []
    for t in range(start, xy.shape[0], every):
        for pa in patches:
            pa.remove()
        patches = []
        corners = _boxes(xy[t], hd[t], size)
        for a in np.nonzero(vd[t])[0]:
            pa = Polygon(corners[a], closed=True, facecolor="#d62728" if a == 0 else "#1f77b4", alpha=0.85, zorder=3)
            ax.add_patch(pa)
            patches.append(pa)
        cx, cy = xy[t, 0]
        ax.set_xlim(cx - view_m, cx + view_m)
        ax.set_ylim(cy - view_m, cy + view_m)
        fig.suptitle(f"{title}  t={0.1 * (t - start):.1f} s", fontsize=8)
        fig.canvas.draw()
        images.append(Image.fromarray(np.asarray(fig.canvas.buffer_rgba())[..., :3]))
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    tmp = path + ".tmp.gif"
    images[0].save(tmp, save_all=True, append_images=images[1:], duration=200, loop=0)
    os.replace(tmp, path)
    return path
