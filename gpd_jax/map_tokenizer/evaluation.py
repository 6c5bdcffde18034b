"""Scoring a map tokenizer: lanes -> (raster ->) tokens -> lanes against the frames' SLEDGE vector lanes.

`evaluate` reports the map metrics of `gpd_jax.metrics.map` (paper-faithful F1 at 1.5 m, precision, recall,
lateral distance, Chamfer; the corrected set-based Chamfer; the cut-invariant `*_cutfree` score beside them; the
reconstruction figures: both F1s at 0.5 / 1.0 / 1.5 m and the share of GT successor pairs kept) plus
the codebook usage and perplexity of the tokens, and the raster-level reconstruction (`raster_sums`: the decoded
lines drawn with the tokenizer's own rasterizer against its input raster); `python -m gpd_jax.map_tokenizer
evaluate` and stage-1 training's validation both use it.
"""

from __future__ import annotations

import functools

import jax
import numpy as np

import jax.numpy as jnp

from gpd_jax.data.lanes import HALF, RECUT_MODES, recut_polylines  # noqa: F401  (re-exported)
from gpd_jax.map_tokenizer import core
from gpd_jax.map_tokenizer.raster import raster_channels, rasterize
from gpd_jax.metrics.matching import match_lines
from gpd_jax.metrics.map import (END_LABELS, LENGTH_EDGES_M, RECONSTRUCTION_THRESHOLDS_M, cutfree_frame_sums,
                                 length_labels, map_metric_sums, reduce_map_metrics, threshold_key)


def rasterize_batch(config, batch):
    """f32[B, 256, 256] rasters of a batch dict (polylines, polyline_valid, pose); f32[B, 256, 256, 3] with
    `raster.direction`."""
    r = config.raster
    return rasterize(batch["polylines"], batch["polyline_valid"], batch["pose"], size=r.size,
                     pixel_size=r.pixel_size, max_segment_length=r.max_segment_length,
                     direction=raster_channels(r) > 1)


FRAME_KEYS = ("polylines", "polyline_valid", "pose", "lanes", "lanes_valid")  # what a compiled step reads of a batch


def frame_arrays(batch: dict) -> dict:
    """The arrays of a batch dict the compiled train and eval steps read (`FRAME_KEYS`)."""
    return {k: batch[k] for k in FRAME_KEYS}


def encoder_input(config, batch):
    """What the tokenizer's encoder reads of a batch dict (polylines, polyline_valid, pose): the raster
    (`rasterize_batch`) for `model.encoder.kind` "raster", the tuple (polylines, polyline_valid, pose) for "vector"."""
    if config.model.encoder.kind == "vector":
        return batch["polylines"], batch["polyline_valid"], batch["pose"]
    return rasterize_batch(config, batch)


RASTER_TOLERANCE_PX = 6  # 1.5 m at 0.25 m per pixel: the raster F1's tolerance, the map F1's threshold


def dilate(raster: jax.Array, radius: int) -> jax.Array:
    """f32[..., H, W] binary raster -> the same with every pixel within `radius` pixels (Chebyshev: a
    (2 radius + 1)^2 square) of a set pixel set."""
    if radius <= 0:
        return raster
    lead = raster.shape[:-2]
    r = raster.reshape((-1,) + raster.shape[-2:])
    k = 2 * radius + 1
    out = jax.lax.reduce_window(r, -jnp.inf, jax.lax.max, (1, k, k), (1, 1, 1), "SAME")
    return out.reshape(lead + raster.shape[-2:])


def raster_sums(decoded: jax.Array, target: jax.Array, tolerance_px: int = RASTER_TOLERANCE_PX
                ) -> dict[str, jax.Array]:
    """Pixel counts comparing rasters f32[B, H, W] (binary) of decoded lines with the input rasters, summed over B.

    Keys: raster_inter / raster_union (exact pixels, IoU = inter / union), raster_dec / raster_tgt (set pixels),
    raster_dec_near (decoded pixels within `tolerance_px` of a target pixel) and raster_tgt_near (target pixels
    within it of a decoded pixel): raster precision / recall at that tolerance.
    """
    d, t = decoded > 0.5, target > 0.5
    dn = dilate(decoded, tolerance_px) > 0.5
    tn = dilate(target, tolerance_px) > 0.5
    s = lambda x: jnp.sum(x.astype(jnp.float32))
    return {"raster_inter": s(d & t), "raster_union": s(d | t), "raster_dec": s(d), "raster_tgt": s(t),
            "raster_dec_near": s(d & tn), "raster_tgt_near": s(t & dn)}


def decoded_raster(config, points: jax.Array, logits: jax.Array) -> jax.Array:
    """Decoded lines f32[B, Q, P, 2] (ego frame) with logits f32[B, Q] drawn by the tokenizer's rasterizer (lines
    with logit > 0) -> f32[B, H, W], the same pixels an input raster of those lines would have."""
    r = config.raster
    valid = jnp.broadcast_to((logits > 0)[..., None], points.shape[:-1])
    return rasterize(points, valid, jnp.zeros(points.shape[:-3] + (3,), points.dtype), size=r.size,
                     pixel_size=r.pixel_size, max_segment_length=r.max_segment_length)


def reduce_raster(s: dict) -> dict[str, float]:
    """`raster_sums` totals -> raster_iou, raster_precision / raster_recall / raster_f1 at the tolerance."""
    f = lambda k: float(np.asarray(s[k]))
    div = lambda a, b: a / b if b > 0 else float("nan")
    p, r = div(f("raster_dec_near"), f("raster_dec")), div(f("raster_tgt_near"), f("raster_tgt"))
    return {"raster_iou": div(f("raster_inter"), f("raster_union")), "raster_precision": p, "raster_recall": r,
            "raster_f1": (2 * p * r / (p + r)) if p + r > 0 else 0.0}


def pair_sums(points, logits, lanes, lanes_valid, threshold: float = 1.5) -> dict[str, jax.Array]:
    """Where the decoded lines differ from their Hungarian-matched GT lines (the paper's matching), summed over
    the batch: pairs (GT line valid, matched prediction with logit > 0), those whose reversed prediction is closer
    (mean index-aligned distance), those with both end points within `threshold` of the GT's, and those whose
    predicted length is over 1.5x / under 1/1.5 of the GT's (the line is cut elsewhere).

    Args: points f32[B, Q, P, 2], logits f32[B, Q], lanes f32[B, L, P, 2], lanes_valid bool[B, L].
    """
    m, ml, _ = match_lines(points, logits, lanes, lanes_valid)
    ok = lanes_valid & (ml > 0)
    d_fwd = jnp.mean(jnp.linalg.norm(m - lanes, axis=-1), -1)
    d_rev = jnp.mean(jnp.linalg.norm(m[..., ::-1, :] - lanes, axis=-1), -1)
    ends = ((jnp.linalg.norm(m[..., 0, :] - lanes[..., 0, :], axis=-1) <= threshold)
            & (jnp.linalg.norm(m[..., -1, :] - lanes[..., -1, :], axis=-1) <= threshold))
    length = lambda x: jnp.sum(jnp.linalg.norm(jnp.diff(x, axis=-2), axis=-1), -1)
    ratio = length(m) / jnp.maximum(length(lanes), 1e-3)
    s = lambda x: jnp.sum((x & ok).astype(jnp.float32))
    return {"pair_n": s(ok), "pair_reversed": s(d_rev < d_fwd), "pair_ends_ok": s(ends),
            "pair_longer": s(ratio > 1.5), "pair_shorter": s(ratio < 1 / 1.5)}


def reduce_pairs(t: dict) -> dict[str, float]:
    """`pair_sums` totals -> shares of the matched pairs."""
    n = float(np.asarray(t["pair_n"]))
    f = lambda k: float(np.asarray(t[k])) / n if n > 0 else float("nan")
    return {"matched_pairs": int(n), "pairs_reversed_share": f("pair_reversed"),
            "pairs_both_ends_within_share": f("pair_ends_ok"), "pairs_pred_longer_1.5x_share": f("pair_longer"),
            "pairs_pred_shorter_1.5x_share": f("pair_shorter")}


def make_eval_step(graphdef, config, diagnostics: bool = True, quantized: bool = True):
    """eval_step(params, frames) -> (map metric sums, token indices) of `frames` (`frame_arrays` of a batch),
    with the paper's and the cut-invariant F1 at every `RECONSTRUCTION_THRESHOLDS_M` and the successor pairs kept
    (`map_metric_sums`'s `connectivity`); with `diagnostics`, also the raster-level reconstruction (`raster_sums`:
    the decoded lines drawn with `config.raster` against the frames' raster) and the matched-pair diagnostics
    (`pair_sums`). `quantized` False decodes the encoder's continuous latents instead of their codes: the figure
    of a model trained without the codebook (`train.kmeans_at_step` beyond its steps), i.e. what the quantiser
    costs; the token indices are still the nearest codes."""

    def eval_step(params, frames):
        out = core.forward(graphdef, params, encoder_input(config, frames), quantized)
        lanes, lanes_valid = frames["lanes"], frames["lanes_valid"]
        sums = map_metric_sums(out["points"], out["logits"], lanes, lanes_valid, length_edges=LENGTH_EDGES_M,
                               window_half=HALF, extra_thresholds=RECONSTRUCTION_THRESHOLDS_M, connectivity=True)
        if diagnostics:
            raster = rasterize_batch(config, frames)
            occupancy = raster[..., 0] if raster.ndim == 4 else raster
            sums.update(raster_sums(decoded_raster(config, out["points"], out["logits"]), occupancy))
            sums.update(pair_sums(out["points"], out["logits"], lanes, lanes_valid))
        return sums, out["idx"]

    return eval_step


def tokenizer_metrics(graphdef, params, config, batches, eval_step=None) -> dict[str, float]:
    """Map metrics (paper-faithful F1 @1.5 m, lateral, Chamfer; corrected Chamfer; the cut-invariant score) plus
    codebook usage and perplexity of the tokens, over an iterable of batch dicts; plus the raster-level
    reconstruction (raster_iou, raster_f1 at 1.5 m, ...) when `eval_step` makes it (the default one does)."""
    eval_step = eval_step or jax.jit(make_eval_step(graphdef, config))
    total = None
    counts = np.zeros((config.model.num_codes,), np.float64)
    frames = 0
    for batch in batches:
        sums, idx = eval_step(params, frame_arrays(batch))
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
        "f1_cutfree": m["map_f1_cutfree"], "precision_cutfree": m["map_precision_cutfree"],
        "recall_cutfree": m["map_recall_cutfree"], "chamfer_cutfree": m["map_chamfer_cutfree"],
        "chamfer_within_cutfree": m["map_chamfer_within_cutfree"],
        **{f"f1@{threshold_key(t)}m": m["map_f1@" + threshold_key(t)] for t in RECONSTRUCTION_THRESHOLDS_M},
        **{f"f1_cutfree@{threshold_key(t)}m": m["map_f1_cutfree@" + threshold_key(t)]
           for t in RECONSTRUCTION_THRESHOLDS_M},
        "connectivity": m["map_connectivity"], "successor_pairs": int(m["map_successor_pairs"]),
        "f1_cutfree_directed": m["map_f1_cutfree_directed"],
        "precision_cutfree_directed": m["map_precision_cutfree_directed"],
        "recall_cutfree_directed": m["map_recall_cutfree_directed"],
        **(reduce_raster(total) if "raster_inter" in total else {}),
        **(reduce_pairs(total) if "pair_n" in total else {}),
        "codebook_usage": float(np.mean(counts > 0)), "perplexity": float(np.exp(-np.sum(nz * np.log(nz)))),
        "frames": frames,
        # diagnostic: the per-point recall for GT lines of each length, and how many GT lines each group has
        "recall_by_gt_length": dict(zip(length_labels(), m["map_recall_by_length"])),
        "gt_lines_by_length": dict(zip(length_labels(), (int(round(x / lanes_points)) for x in
                                                         m["map_gt_points_by_length"]))),
        # ... and for GT lines by how many ends lie inside the window (junctions, lane ends) rather than on its
        # border: where the paper's F1 loses its points (docs/tokenizer.md)
        "recall_by_gt_ends": dict(zip(END_LABELS, m["map_recall_by_ends"])),
        "gt_lines_by_ends": dict(zip(END_LABELS, (int(round(x / lanes_points)) for x in m["map_gt_points_by_ends"]))),
    }


# ------------------------------------------------------------------------------------------ GT cut diagnostics
# The re-cut rules (`RECUT_MODES`, `recut_polylines`) live in the data layer: the tokenizer can also train on
# them (`data.gt_recut`). "join_chunks" is left out of the probe: the vector lanes join the store's chunks anyway.
PROBE_MODES = tuple(m for m in RECUT_MODES if m != "join_chunks")


def cut_diagnostics(batches, threshold: float = 1.5, dense_points: int = 80) -> dict:
    """How the GT vector lanes cut the road, and how much the paper's F1 punishes the cut alone.

    Over an iterable of `frame_batches` dicts (polylines, polyline_valid, pose, lanes, lanes_valid):
      * runs_per_frame (lines before the 50 nearest are kept), share of frames with more than 50, share of runs
        dropped by that cap; GT line lengths (quantiles, share < 5 m);
      * the 20-point representation: the cut-invariant score of the 20-point GT against the same runs at
        `dense_points` points (what resampling each line to 20 points loses on curves);
      * the learnability probe: for each `PROBE_MODES` mode, the same road re-cut (`recut_polylines`) and
        turned into vector lanes by the same rules, scored as a perfect prediction (logit +10) against the GT:
        the paper's F1 (and with exact hits counted), the cut-invariant F1, and the share of frames whose lines
        changed.
    """
    from gpd_jax.data.lanes import NUM_LINES, NUM_POINTS, vector_lanes
    from gpd_jax.metrics.map import map_metric_sums, reduce_cutfree, reduce_map_metrics

    sums_fn = jax.jit(map_metric_sums, static_argnames=("threshold", "count_exact_hits", "length_edges"))
    acc: dict = {}
    runs, lengths, frames = [], [], 0
    changed = {m: 0 for m in PROBE_MODES}

    def add(name, s):
        s = jax.device_get(s)
        acc[name] = s if name not in acc else {k: acc[name][k] + s[k] for k in s}

    for b in batches:
        n = b["pose"].shape[0]
        frames += n
        dense, dense_ok = [], []
        for i in range(n):
            many, many_ok = vector_lanes(b["polylines"][i], b["polyline_valid"][i], b["pose"][i], num_lines=1000)
            runs.append(int(many_ok.sum()))
            d, dok = vector_lanes(b["polylines"][i], b["polyline_valid"][i], b["pose"][i],
                                  num_points=dense_points)
            dense.append(d), dense_ok.append(dok)
        gt, gv = b["lanes"], b["lanes_valid"]
        seg = np.linalg.norm(np.diff(gt, axis=-2), axis=-1).sum(-1)
        lengths.extend(seg[gv].tolist())
        # 20 points against the same runs at dense_points points: resample both to the dense count's line set
        dense, dense_ok = np.stack(dense), np.stack(dense_ok)
        add("dense", _cutfree_only(gt, gv, dense, dense_ok, 0.25))
        for mode in PROBE_MODES:
            rl, rok = [], []
            for i in range(n):
                pp, pv = recut_polylines(b["polylines"][i], b["polyline_valid"][i], mode)
                lz, lok = vector_lanes(pp, pv, b["pose"][i])
                rl.append(lz), rok.append(lok)
                changed[mode] += int(not (np.array_equal(lok, gv[i]) and np.allclose(lz, gt[i], atol=1e-4)))
            rl, rok = np.stack(rl).astype(np.float32), np.stack(rok)
            logits = np.where(rok, 10.0, -10.0).astype(np.float32)
            add(mode, sums_fn(rl, logits, gt, gv, threshold=threshold))
            add(mode + "_exact", sums_fn(rl, logits, gt, gv, threshold=threshold, count_exact_hits=True))
    if not frames:
        raise ValueError("cut_diagnostics got no batches")
    runs_a, len_a = np.asarray(runs), np.asarray(lengths)
    out = {"frames": frames, "runs_per_frame_mean": float(runs_a.mean()),
           "runs_per_frame_p90": float(np.percentile(runs_a, 90)), "runs_per_frame_max": int(runs_a.max()),
           "frames_over_cap_share": float(np.mean(runs_a > NUM_LINES)),
           "runs_dropped_by_cap_share": float(np.maximum(runs_a - NUM_LINES, 0).sum() / max(runs_a.sum(), 1)),
           "gt_lines_per_frame_mean": float(len(len_a) / frames),
           "gt_line_length_m": {q: float(np.percentile(len_a, int(q[1:]))) for q in ("p10", "p50", "p90")},
           "gt_line_length_mean_m": float(len_a.mean()),
           "gt_lines_under_5m_share": float(np.mean(len_a < 5.0)),
           "gt_point_spacing_median_m": float(np.median(len_a) / (NUM_POINTS - 1))}
    d = reduce_cutfree(acc["dense"])
    out[f"gt{NUM_POINTS}_vs_{dense_points}pts"] = {"f1_cutfree_at_0.25m": d["map_f1_cutfree"],
                                                   "chamfer_cutfree_m": d["map_chamfer_cutfree"]}
    for mode in PROBE_MODES:
        r, rx = reduce_map_metrics(acc[mode]), reduce_map_metrics(acc[mode + "_exact"])
        out[f"recut_{mode}"] = {"paper_f1": r["map_f1"], "paper_f1_exact_hits": rx["map_f1"],
                                "f1_cutfree": r["map_f1_cutfree"], "chamfer_cutfree_m": r["map_chamfer_cutfree"],
                                "frames_changed_share": changed[mode] / frames}
    return out


@functools.partial(jax.jit, static_argnames=("threshold",))
def _cutfree_only(pred, pred_ok, gt, gt_ok, threshold):
    """Cut-invariant sums f32[1] of lines f32[B, L, P, 2] (existing where pred_ok) against f32[B, L', P', 2]."""
    s = jax.vmap(lambda a, b, c, d: cutfree_frame_sums(a, b, c, d, threshold=threshold))(
        jnp.asarray(pred, jnp.float32), pred_ok, jnp.asarray(gt, jnp.float32), gt_ok)
    return {k: jnp.sum(v)[None] for k, v in s.items()}
