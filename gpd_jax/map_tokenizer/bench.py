"""Throughput of the rasterizer and of the two assignment solvers (`python -m gpd_jax.map_tokenizer bench`), and
the encoding speed of tokenizers side by side (`bench --encoders A B`).

Inputs are synthetic but sized like the data store (96 polylines x 128 points at 1 m) and like training
(50 x 50 matching costs of a half-trained decoder: GT lines plus noise, permuted, random logits).
"""

from __future__ import annotations

import time

import jax
import jax.numpy as jnp
import numpy as np

from gpd_jax.map_tokenizer.auction import auction
from gpd_jax.map_tokenizer.raster import rasterize
from gpd_jax.map_tokenizer.synthetic import synthetic_lanes
from gpd_jax.metrics.matching import hungarian, line_match_cost


def _time(f, *args, reps: int = 5) -> float:
    jax.block_until_ready(f(*args))
    t0 = time.perf_counter()
    for _ in range(reps):
        jax.block_until_ready(f(*args))
    return (time.perf_counter() - t0) / reps


def raster_inputs(batch: int, lines: int = 96, points: int = 128, seed: int = 0):
    rng = np.random.default_rng(seed)
    start = rng.uniform(-60, 60, (batch, lines, 1, 2))
    ang = rng.uniform(-np.pi, np.pi, (batch, lines, 1))
    s = np.arange(points)[None, None, :]
    pts = (start + np.stack([np.cos(ang) * s, np.sin(ang) * s], -1)).astype(np.float32)
    n_valid = rng.integers(10, points, (batch, lines, 1))
    valid = s < n_valid
    pose = np.concatenate([rng.uniform(-5, 5, (batch, 2)), rng.uniform(-np.pi, np.pi, (batch, 1))], -1)
    return jnp.asarray(pts), jnp.asarray(valid), jnp.asarray(pose.astype(np.float32))


def matching_costs(batch: int, seed: int = 0) -> tuple[jax.Array, np.ndarray]:
    """(cost f32[batch, 50, 50], GT validity bool[batch, 50])."""
    d = synthetic_lanes(seed, batch)
    rng = np.random.default_rng(seed + 1)
    perm = np.stack([rng.permutation(50) for _ in range(batch)])
    pred = np.take_along_axis(d["lanes"], perm[:, :, None, None], 1) + rng.normal(0, 2.0, d["lanes"].shape)
    logits = rng.normal(0, 2.0, (batch, 50))
    return line_match_cost(jnp.asarray(pred, jnp.float32), jnp.asarray(logits, jnp.float32), d["lanes"],
                           d["lanes_valid"]), d["lanes_valid"]


def run(batch: int = 64) -> dict:
    out = {"device": str(jax.devices()[0]), "batch": batch}
    pts, valid, pose = raster_inputs(batch)
    for msl in (1.0, 2.0):  # 4 or 8 samples per segment
        f = jax.jit(lambda a, b, c, m=msl: rasterize(a, b, c, max_segment_length=m))
        out[f"rasters_per_s_max_segment_{msl:g}m"] = batch / _time(f, pts, valid, pose)
    for b in (32, 256):
        cost, gt_valid = matching_costs(b)
        t_h = _time(jax.jit(hungarian), cost)
        t_a = _time(jax.jit(auction), cost, reps=1)
        m_h, m_a = jax.jit(hungarian)(cost), jax.jit(auction)(cost)  # (cached compiles)
        total = lambda m: jnp.sum(jnp.take_along_axis(cost, m[:, None, :], 1)[:, 0], -1)
        gap = float(jnp.max(total(m_a) - total(m_h)))
        out[f"match_b{b}"] = {"scipy_callback_ms": 1e3 * t_h, "jax_auction_ms": 1e3 * t_a,
                              "auction_max_total_cost_gap": gap,
                              # padded GT slots are interchangeable (equal costs): compare the real lines only
                              "identical_on_valid_gt": float(np.mean(np.all((np.asarray(m_h) == np.asarray(m_a))
                                                                            | ~gt_valid, -1)))}
    return out


def encode_speed(tokenizers, names, batch: int = 64, reps: int = 5) -> dict:
    """Frames per second of each tokenizer's `encode_lanes` (lanes -> tokens: the raster encoder's time includes
    drawing the raster) on the same synthetic frames (`raster_inputs`), jitted, in one run; `ratio_to_first` is
    each speed over the first tokenizer's."""
    pts, valid, pose = raster_inputs(batch)
    out = {"device": str(jax.devices()[0]), "batch": batch,
           "frames": f"{pts.shape[1]} polylines x {pts.shape[2]} points"}
    speeds = []
    for tok, name in zip(tokenizers, names):
        f = jax.jit(lambda p, a, b, c, tok=tok: tok.encode_lanes(p, a, b, c))
        speeds.append(batch / _time(f, tok.params, pts, valid, pose, reps=reps))
        out[name] = {"encoder": tok.config.model.encoder.kind, "frames_per_s": speeds[-1],
                     "ratio_to_first": speeds[-1] / speeds[0]}
    return out
