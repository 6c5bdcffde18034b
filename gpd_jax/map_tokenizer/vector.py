"""The vector map encoder: a frame's lane polylines -> a set of lane segments -> one latent per 8 m cell.

The raster encoder (`model.Encoder`) first draws the lanes into a 256 x 256 picture and then has to learn to see
one-pixel lines again; this one reads the polylines themselves (the lanes arrive as vectors):

1. `lane_segments`: the polylines (scene frame) are moved into the frame's ego frame, each row's valid points are
   packed to the front, and the row is cut into segments of `point_stride` points (2: about 2 m at the stores' 1 m
   spacing; a row's last segment ends at its last point). The `max_segments` segments whose midpoints lie nearest
   the ego (Chebyshev distance, within the window plus `cell_margin`) are kept; the rest are masked.
2. Each segment becomes a feature vector (start, end, midpoint, unit direction, length, Fourier features of the
   midpoint: position and heading, nothing about which polyline or which index it came from) and an MLP embeds it.
3. One query per token cell (the raster encoder's 8 x 8 grid, row 0 in front, column 0 on the left) cross-attends to
   the segments whose midpoints lie in its cell widened by `cell_margin` metres (a validity mask; a learned "empty"
   key lets a cell with no lanes attend to something), then the cells attend to each other; `num_layers` times.
4. A linear head gives the code-dim latent of each cell, quantized and decoded exactly as the raster encoder's.

Why cells rather than free learned queries: the tokens keep the raster grid's meaning (token k describes cell k), so
the GPD reads them with the same position embedding and the tokenizer's `warper` can tell which cells a moved
window has not seen; the mask makes that true (a cell's token depends on the lanes near it only).

Invariances (tests/test_vector_tokenizer.py): the tokens do not depend on the order of the polylines, on padding
rows, or on where a row's valid points sit in it (a set of segments with masks, no index features). They do depend
on a lane's direction (segments point along the travel direction).
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import ml_collections
from flax import nnx

from gpd_jax.map_tokenizer.raster import cell_centres, sine_position_2d, to_ego_frame


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Segments:
    """The lane segments a vector encoder reads, in the ego frame (metres).

    start: f32[B, N, 2]; end: f32[B, N, 2]; valid: bool[B, N] (False: padding, its points are zero).
    """

    start: jax.Array
    end: jax.Array
    valid: jax.Array


def _pack_valid(points: jax.Array, valid: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Each row's valid points moved to its front in their order: (f32[..., P, 2], count i32[...])."""
    order = jnp.argsort(~valid, axis=-1, stable=True)
    return jnp.take_along_axis(points, order[..., None], axis=-2), jnp.sum(valid, -1)


def lane_segments(polylines: jax.Array, valid: jax.Array, pose: jax.Array, half: float, margin: float,
                  point_stride: int, max_segments: int) -> Segments:
    """The segments of lane polylines seen from an ego pose (step 1 of the module docstring).

    Args:
      polylines: f32[B, L, P, 2] in the scene frame; valid: bool[B, L, P]; pose: f32[B, 3] the frame's ego pose.
      half: half the window's side (m); margin: segments whose midpoint lies up to this far outside still count.
      point_stride: points per segment (>= 1); max_segments: N, the segments kept (nearest the ego first).
    """
    pts = to_ego_frame(polylines, pose[:, None, :])
    pts, count = _pack_valid(pts, valid)
    p = pts.shape[-2]
    first = jnp.arange(0, p - 1, point_stride)  # [S] start index of each segment of a row
    last = jnp.maximum(count - 1, 0)[..., None]  # [B, L, 1] index of a row's last valid point
    end_i = jnp.minimum(first + point_stride, last)  # [B, L, S]
    ok = first < last  # at least one more valid point after the start
    a = pts[..., first, :]  # [B, L, S, 2]
    b = jnp.take_along_axis(pts, end_i[..., None], axis=-2)
    mid = 0.5 * (a + b)
    dist = jnp.max(jnp.abs(mid), -1)
    ok = ok & (dist <= half + margin)
    bsz = pts.shape[0]
    a, b, ok, dist = (x.reshape((bsz, -1) + x.shape[3:]) for x in (a, b, ok, dist))
    n = min(max_segments, ok.shape[1])
    _, idx = jax.lax.top_k(jnp.where(ok, -dist, -jnp.inf), n)
    take = lambda x: jnp.take_along_axis(x, idx[..., None] if x.ndim == 3 else idx, axis=1)
    keep = take(ok)
    zero = lambda x: jnp.where(keep[..., None], x, 0.0)
    return Segments(start=zero(take(a)), end=zero(take(b)), valid=keep)


def segment_features(seg: Segments, half: float, fourier: int) -> jax.Array:
    """f32[B, N, F] per-segment features (step 2), coordinates scaled by 1 / `half`."""
    a, b = seg.start / half, seg.end / half
    d = b - a
    length = jnp.linalg.norm(d, axis=-1, keepdims=True)
    unit = d / jnp.maximum(length, 1e-6)
    mid = 0.5 * (a + b)
    freq = jnp.pi * 2.0 ** jnp.arange(fourier, dtype=jnp.float32)  # [F]
    ang = mid[..., None, :] * freq[:, None]  # [B, N, F, 2]
    four = jnp.concatenate([jnp.sin(ang), jnp.cos(ang)], -1).reshape(mid.shape[:-1] + (4 * fourier,))
    heading = jnp.concatenate([unit, jnp.stack([unit[..., 0] ** 2 - unit[..., 1] ** 2,
                                                2 * unit[..., 0] * unit[..., 1]], -1)], -1)  # angle and double angle
    f = jnp.concatenate([a, b, mid, heading, length * half / 4.0, four], -1)
    return jnp.where(seg.valid[..., None], f, 0.0)


def num_segment_features(fourier: int) -> int:
    return 2 + 2 + 2 + 4 + 1 + 4 * fourier


def cell_mask(seg: Segments, grid: int, half: float, margin: float) -> jax.Array:
    """bool[B, M, N]: segment n is seen by cell m (its midpoint within the cell widened by `margin`)."""
    mid = 0.5 * (seg.start + seg.end)
    centres = cell_centres(grid, half)
    reach = half / grid + margin
    inside = jnp.max(jnp.abs(mid[:, None, :, :] - centres[None, :, None, :]), -1) <= reach
    return inside & seg.valid[:, None, :]


class CellLayer(nnx.Module):
    """Pre-norm: cells cross-attend to their segments (masked, plus a learned empty key), attend to each other, FFN."""

    def __init__(self, d: int, heads: int, ffn: int, rngs: nnx.Rngs):
        self.n1 = nnx.LayerNorm(d, rngs=rngs)
        self.cross = nnx.MultiHeadAttention(heads, d, decode=False, rngs=rngs)
        self.n2 = nnx.LayerNorm(d, rngs=rngs)
        self.self_attn = nnx.MultiHeadAttention(heads, d, decode=False, rngs=rngs)
        self.n3 = nnx.LayerNorm(d, rngs=rngs)
        self.ff1 = nnx.Linear(d, ffn, rngs=rngs)
        self.ff2 = nnx.Linear(ffn, d, rngs=rngs)

    def __call__(self, x, pos, memory, mask):
        """x f32[B, M, d] cells, pos f32[1, M, d], memory f32[B, N + 1, d], mask bool[B, M, N + 1]."""
        h = self.n1(x) + pos
        x = x + self.cross(h, memory, memory, mask=mask[:, None], deterministic=True)
        h = self.n2(x) + pos
        x = x + self.self_attn(h, h, h, deterministic=True)
        return x + self.ff2(jax.nn.relu(self.ff1(self.n3(x))))


class VectorEncoder(nnx.Module):
    """Lane polylines -> latents f32[B, grid * grid, code_dim] (module docstring). `cfg` is `model.vector`."""

    def __init__(self, cfg: ml_collections.ConfigDict, grid: int, half: float, code_dim: int, rngs: nnx.Rngs):
        d = int(cfg.d_model)
        self.grid, self.half = int(grid), float(half)
        self.margin, self.stride = float(cfg.cell_margin), int(cfg.point_stride)
        self.max_segments, self.fourier = int(cfg.max_segments), int(cfg.fourier)
        if self.stride < 1 or self.max_segments < 1:
            raise ValueError(f"model.vector: point_stride {self.stride} and max_segments {self.max_segments} "
                             "must be >= 1")
        self.seg1 = nnx.Linear(num_segment_features(self.fourier), d, rngs=rngs)
        self.seg2 = nnx.Linear(d, d, rngs=rngs)
        self.seg_norm = nnx.LayerNorm(d, rngs=rngs)
        self.empty = nnx.Param(jax.random.normal(rngs.params(), (1, 1, d)) * 0.02)
        self.cells = nnx.Param(jax.random.normal(rngs.params(), (self.grid * self.grid, d)) * 0.02)
        self.layers = nnx.List([CellLayer(d, int(cfg.num_heads), int(cfg.ffn_dim), rngs)
                                for _ in range(int(cfg.num_layers))])
        self.norm = nnx.LayerNorm(d, rngs=rngs)
        self.out = nnx.Linear(d, code_dim, rngs=rngs)

    def segments(self, polylines, valid, pose) -> Segments:
        return lane_segments(polylines, valid, pose, self.half, self.margin, self.stride, self.max_segments)

    def __call__(self, lanes: tuple[jax.Array, jax.Array, jax.Array]) -> jax.Array:
        """lanes = (polylines f32[B, L, P, 2] scene frame, valid bool[B, L, P], pose f32[B, 3]) -> f32[B, M, D]."""
        seg = self.segments(*lanes)
        b = seg.valid.shape[0]
        f = segment_features(seg, self.half, self.fourier)
        memory = self.seg_norm(self.seg2(jax.nn.relu(self.seg1(f))))
        memory = jnp.concatenate([jnp.broadcast_to(self.empty[...], (b, 1, memory.shape[-1])), memory], 1)
        mask = cell_mask(seg, self.grid, self.half, self.margin)
        mask = jnp.concatenate([jnp.ones(mask.shape[:2] + (1,), bool), mask], -1)
        pos = sine_position_2d(self.grid, self.grid, memory.shape[-1])[None]
        x = jnp.broadcast_to(self.cells[...][None], (b,) + self.cells.shape)
        for layer in self.layers:
            x = layer(x, pos, memory, mask)
        return self.out(self.norm(x))
