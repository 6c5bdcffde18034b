"""Scoring a map tokenizer: raster -> tokens -> lanes against the frames' SLEDGE vector lanes.

`evaluate` reports the map metrics of `gpd_jax.metrics.map` (paper-faithful F1 at 1.5 m, precision, recall,
lateral distance, Chamfer; the corrected set-based Chamfer) plus the codebook usage and perplexity of the
tokens; `python -m gpd_jax.map_tokenizer evaluate` and stage-1 training's validation both use it.
"""

from __future__ import annotations

import jax
import numpy as np

from gpd_jax.map_tokenizer import core
from gpd_jax.map_tokenizer.raster import rasterize
from gpd_jax.metrics.map import LENGTH_EDGES_M, length_labels, map_metric_sums, reduce_map_metrics


def rasterize_batch(config, batch):
    """f32[B, 256, 256] rasters of a batch dict (polylines, polyline_valid, pose)."""
    r = config.raster
    return rasterize(batch["polylines"], batch["polyline_valid"], batch["pose"], size=r.size,
                     pixel_size=r.pixel_size, max_segment_length=r.max_segment_length)


def make_eval_step(graphdef):
    def eval_step(params, raster, lanes, lanes_valid):
        out = core.forward(graphdef, params, raster)
        sums = map_metric_sums(out["points"], out["logits"], lanes, lanes_valid, length_edges=LENGTH_EDGES_M)
        return sums, out["idx"]

    return eval_step


def evaluate(graphdef, params, config, batches, eval_step=None) -> dict[str, float]:
    """Map metrics (paper-faithful F1 @1.5 m, lateral, Chamfer; corrected Chamfer) plus codebook usage and
    perplexity of the tokens, over an iterable of batch dicts."""
    eval_step = eval_step or jax.jit(make_eval_step(graphdef))
    raster_fn = jax.jit(lambda b: rasterize_batch(config, b))
    total = None
    counts = np.zeros((config.model.num_codes,), np.float64)
    frames = 0
    for batch in batches:
        sums, idx = eval_step(params, raster_fn(batch), batch["lanes"], batch["lanes_valid"])
        sums = jax.device_get(sums)
        total = sums if total is None else {k: total[k] + sums[k] for k in total}
        counts += np.bincount(np.asarray(idx).reshape(-1), minlength=counts.size)
        frames += int(np.shape(batch["lanes_valid"])[0])
    if total is None:
        raise ValueError("evaluation got no batches")
    lanes_points = int(np.shape(batch["lanes"])[-2])
    m = reduce_map_metrics(total)
    p = counts / max(counts.sum(), 1.0)
    nz = p[p > 0]
    return {
        "f1": m["map_f1"], "precision": m["map_precision"], "recall": m["map_recall"],
        "lateral": m["map_lateral"], "chamfer": m["map_chamfer"],
        "chamfer_corrected": m["map_chamfer_corrected"],
        "chamfer_corrected_skipped": m["map_chamfer_corrected_skipped"],
        "codebook_usage": float(np.mean(counts > 0)), "perplexity": float(np.exp(-np.sum(nz * np.log(nz)))),
        "frames": frames,
        # diagnostic: the per-point recall for GT lines of each length, and how many GT lines each group has
        "recall_by_gt_length": dict(zip(length_labels(), m["map_recall_by_length"])),
        "gt_lines_by_length": dict(zip(length_labels(), (int(round(x / lanes_points)) for x in
                                                         m["map_gt_points_by_length"]))),
    }
