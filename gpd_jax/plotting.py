"""Pieces every picture of the package shares (matplotlib): a scale bar in metres and a legend band under the scene.
The rollout pictures (`gpd_jax.evaluation.render`) and the closed-loop ones (`gpd_jax.sim.render`) use them."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, NamedTuple

import numpy as np


class Picture(NamedTuple):
    """A picture drawn once and updated frame by frame: `draw(t)` -> uint8[size_px, size_px, 3]. `legend` (a
    matplotlib Legend; None where the picture is too small for one) and `scale_bar` (an AnchoredSizeBar) are what
    a reader needs to read it; `labels` are the legend's entries."""
    fig: Any
    ax: Any
    legend: Any
    scale_bar: Any
    labels: tuple[str, ...]
    draw: Callable[[int], np.ndarray]


def scale_bar_m(view_m: float) -> float:
    """A round scale-bar length (1, 2 or 5 x 10^k metres) of at most a quarter of a view 2 * `view_m` wide."""
    limit = max(0.5 * view_m, 1e-9)
    k = 10.0 ** np.floor(np.log10(limit))
    return float(max(m * k for m in (1.0, 2.0, 5.0, 10.0) if m * k <= limit * (1 + 1e-9)))


def add_scale_bar(ax, view_m: float, fontsize: float):
    """A scale bar in metres at the lower right of `ax` (data units: metres, equal aspect). Returns the artist,
    whose label is `artist.txt_label.get_text()`."""
    from matplotlib.font_manager import FontProperties
    from mpl_toolkits.axes_grid1.anchored_artists import AnchoredSizeBar

    length = scale_bar_m(view_m)
    bar = AnchoredSizeBar(ax.transData, length, f"{length:g} m", loc="lower right", pad=0.25, borderpad=0.3, sep=2,
                          frameon=True, size_vertical=view_m / 120, color="black",
                          fontproperties=FontProperties(size=fontsize))
    bar.patch.set(facecolor="white", alpha=0.75, edgecolor="none")
    bar.set_zorder(20)
    ax.add_artist(bar)
    return bar


def legend_band(fig, ax, handles, labels, fontsize: float, top: float):
    """A figure legend in a band under `ax` (never over the scene): as many columns as fit the width, then `ax`
    is moved to fill the space between the band and `top` (figure fraction). Returns the legend."""
    renderer = fig.canvas.get_renderer()
    for ncol in (3, 2, 1):
        leg = fig.legend(handles, labels, loc="lower left", bbox_to_anchor=(0.0, 0.0), ncol=ncol, fontsize=fontsize,
                         frameon=False, handlelength=1.6, handleheight=0.9, handletextpad=0.4, columnspacing=0.9,
                         borderaxespad=0.15, labelspacing=0.25)
        box = leg.get_window_extent(renderer).transformed(fig.transFigure.inverted())
        if box.x1 <= 1.0 or ncol == 1:
            break
        leg.remove()
    ax.set_position((0.0, box.y1 + 0.005, 1.0, max(0.1, top - box.y1 - 0.005)))
    return leg
