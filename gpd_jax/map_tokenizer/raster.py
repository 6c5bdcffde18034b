"""Binary bird's-eye rasters of lane polylines around an ego pose (pure JAX; jit, vmap, any batch dims).

Convention (the same as `gpd_jax.scene.Scene.map_tokens`): the raster is `size x size` pixels of
`pixel_size` metres, i.e. 256 x 256 at 0.25 m = 64 x 64 m centred on the ego, in the ego frame
(x forward, y left). **Rows follow x from front to back** (row 0 is the far front edge, x = +32 m) and
**columns follow y from left to right** (column 0 is the far left edge, y = +32 m): a picture with the ego
driving "up". A point (x, y) in the ego frame lands in pixel

    row = floor((half - x) / pixel_size),   col = floor((half - y) / pixel_size),   half = size * pixel_size / 2,

so the ego itself is at pixel (128, 128) and the 8 x 8 token grid over the raster is row-major from the
front-left cell. Points outside the window are dropped.

Lines are one pixel wide (as SLEDGE / GPD-1 with `line_dots_radius = 0`). Each segment between two
consecutive *valid* points is sampled at `samples_per_segment` evenly spaced points. While consecutive
samples are at most one pixel apart, each step moves at most one pixel along each axis, so the drawn line is
8-connected (no gaps): with the default (`max_segment_length = 2 m` -> 8 samples per segment at 0.25 m/px)
this holds for every segment up to 2 m long, i.e. for polylines resampled every ~1 m as the data store does.
Longer segments are still drawn, with gaps of `length / samples_per_segment`.

The batch is drawn with one flat scatter over all rasters (no per-sample loop), which is what makes it fast.

Directional rasters (`direction=True`, a tokenizer's `raster.direction`): three channels per pixel,
(occupancy, cos, sin) of the heading of the segment drawn there in the ego frame (zeros where no line passes),
as SLEDGE's line channels carry the heading; a binary raster cannot tell which way a lane runs, so a decoder
must guess the point order of every line (right-hand traffic is what it learns), which the paper's
index-aligned F1 punishes on left-hand and one-way roads.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp

RASTER_SIZE = 256
PIXEL_SIZE = 0.25


def to_ego_frame(points: jax.Array, pose: jax.Array) -> jax.Array:
    """Expresses points in the frame of `pose`.

    Args:
      points: f32[..., N, 2] in the frame the pose is given in (any number of middle dims is fine as long
        as `pose` broadcasts after the trailing 2 is dropped; see `rasterize`).
      pose: f32[..., 3] (x, y, heading).

    Returns:
      f32[..., N, 2] with `R(-heading) @ (p - (x, y))`.
    """
    c, s = jnp.cos(pose[..., 2]), jnp.sin(pose[..., 2])
    d = points - pose[..., None, :2]
    x = c[..., None] * d[..., 0] + s[..., None] * d[..., 1]
    y = -s[..., None] * d[..., 0] + c[..., None] * d[..., 1]
    return jnp.stack([x, y], axis=-1)


def from_ego_frame(points: jax.Array, pose: jax.Array) -> jax.Array:
    """The inverse of `to_ego_frame`: points f32[..., N, 2] in the frame of `pose` f32[..., 3] -> the frame the
    pose is given in (`R(heading) @ p + (x, y)`)."""
    c, s = jnp.cos(pose[..., 2]), jnp.sin(pose[..., 2])
    x = c[..., None] * points[..., 0] - s[..., None] * points[..., 1]
    y = s[..., None] * points[..., 0] + c[..., None] * points[..., 1]
    return jnp.stack([x, y], axis=-1) + pose[..., None, :2]


def sine_position_2d(h: int, w: int, dim: int, temperature: float = 10000.0) -> jax.Array:
    """DETR's 2-D sine position code f32[h*w, dim] (half the channels for rows, half for columns), row-major."""
    if dim % 4:
        raise ValueError(f"dim {dim} must be a multiple of 4")
    n = dim // 4
    freq = 1.0 / temperature ** (jnp.arange(n, dtype=jnp.float32) / n)
    ys = (jnp.arange(h, dtype=jnp.float32) + 0.5) / h * 2 * jnp.pi
    xs = (jnp.arange(w, dtype=jnp.float32) + 0.5) / w * 2 * jnp.pi
    py = ys[:, None] * freq  # [h, n]
    px = xs[:, None] * freq  # [w, n]
    py = jnp.concatenate([jnp.sin(py), jnp.cos(py)], -1)  # [h, 2n]
    px = jnp.concatenate([jnp.sin(px), jnp.cos(px)], -1)  # [w, 2n]
    grid = jnp.concatenate([jnp.broadcast_to(py[:, None], (h, w, 2 * n)),
                            jnp.broadcast_to(px[None, :], (h, w, 2 * n))], -1)
    return grid.reshape(h * w, dim)


def cell_centres(grid: int, half: float) -> jax.Array:
    """f32[grid * grid, 2] ego-frame centres of the token cells over the window of half side `half`, row-major:
    row 0 in front (largest x), column 0 on the left (largest y), as the raster's pixels."""
    cell = 2.0 * half / grid
    c = half - cell * (jnp.arange(grid, dtype=jnp.float32) + 0.5)  # x of rows, y of columns
    return jnp.stack(jnp.broadcast_arrays(c[:, None], c[None, :]), -1).reshape(-1, 2)


def raster_channels(raster_config) -> int:
    """Channels of a tokenizer's rasters: 3 with `raster.direction` (occupancy, cos, sin), else 1."""
    return 3 if bool(raster_config.direction) else 1


def samples_per_segment(max_segment_length: float = 2.0, pixel_size: float = PIXEL_SIZE) -> int:
    """Samples per segment so that a segment up to `max_segment_length` metres is drawn without gaps."""
    return max(1, int(math.ceil(max_segment_length / pixel_size)))


def pixel_index(xy: jax.Array, size: int = RASTER_SIZE, pixel_size: float = PIXEL_SIZE):
    """(row i32[...], col i32[...], inside bool[...]) of ego-frame points `xy: f32[..., 2]`."""
    half = size * pixel_size / 2.0
    row = jnp.floor((half - xy[..., 0]) / pixel_size).astype(jnp.int32)
    col = jnp.floor((half - xy[..., 1]) / pixel_size).astype(jnp.int32)
    inside = (row >= 0) & (row < size) & (col >= 0) & (col < size)
    return row, col, inside


def rasterize(polylines: jax.Array, valid: jax.Array, pose: jax.Array, *, size: int = RASTER_SIZE,
              pixel_size: float = PIXEL_SIZE, max_segment_length: float = 2.0, direction: bool = False) -> jax.Array:
    """Draws lane polylines into a binary raster around an ego pose.

    Args:
      polylines: f32[..., L, P, 2] lane points, in the same frame as `pose` (e.g. the scene frame).
      valid: bool[..., L, P] which points exist; a segment is drawn between points p and p+1 of a line when
        both are valid; an isolated valid point is drawn as one pixel.
      pose: f32[..., 3] ego (x, y, heading) in the polylines' frame; the raster is centred on it and rotated
        so that the ego heading points to row 0.
      size: raster side in pixels (256).
      pixel_size: metres per pixel (0.25).
      max_segment_length: longest segment (metres) guaranteed to be drawn without gaps; sets the static
        number of samples per segment (`ceil(max_segment_length / pixel_size)`).
      direction: also the heading of the lines (module docstring).

    Returns:
      f32[..., size, size] with 1.0 on pixels a line passes through and 0.0 elsewhere; with `direction`,
      f32[..., size, size, 3]: that occupancy, then cos and sin of the drawn segment's heading in the ego frame
      (an isolated valid point, which has no heading, draws (1, 0, 0)).
    """
    polylines = jnp.asarray(polylines, jnp.float32)
    valid = jnp.asarray(valid, bool)
    pose = jnp.asarray(pose, jnp.float32)
    lead = jnp.broadcast_shapes(polylines.shape[:-3], valid.shape[:-2], pose.shape[:-1])
    L, P = polylines.shape[-3], polylines.shape[-2]
    polylines = jnp.broadcast_to(polylines, lead + (L, P, 2)).reshape((-1, L * P, 2))
    valid = jnp.broadcast_to(valid, lead + (L, P)).reshape((-1, L, P))
    pose = jnp.broadcast_to(pose, lead + (3,)).reshape((-1, 3))
    B = polylines.shape[0]

    local = to_ego_frame(polylines, pose).reshape((B, L, P, 2))
    S = samples_per_segment(max_segment_length, pixel_size)
    t = (jnp.arange(S, dtype=jnp.float32) / S)[:, None]  # [S, 1], endpoint excluded (the vertex draws it)
    a, b = local[:, :, :-1, None, :], local[:, :, 1:, None, :]  # [B, L, P-1, 1, 2]
    seg_pts = a + t * (b - a)  # [B, L, P-1, S, 2]
    seg_ok = jnp.broadcast_to((valid[:, :, :-1] & valid[:, :, 1:])[..., None], seg_pts.shape[:-1])
    pts = jnp.concatenate([seg_pts.reshape((B, -1, 2)), local.reshape((B, -1, 2))], axis=1)
    ok = jnp.concatenate([seg_ok.reshape((B, -1)), valid.reshape((B, -1))], axis=1)

    row, col, inside = pixel_index(pts, size, pixel_size)
    hw = size * size
    flat = jnp.arange(B, dtype=jnp.int32)[:, None] * hw + row * size + col
    flat = jnp.where(ok & inside, flat, B * hw)  # out-of-range index: dropped by the scatter
    if direction:
        seg = b[..., 0, :] - a[..., 0, :]  # [B, L, P-1, 2]
        norm = jnp.linalg.norm(seg, axis=-1, keepdims=True)
        unit = jnp.where(norm > 0, seg / jnp.where(norm > 0, norm, 1.0), jnp.array([0.0, 0.0]))
        seg_dir = jnp.broadcast_to(unit[..., None, :], seg_pts.shape).reshape((B, -1, 2))
        # A vertex takes its outgoing segment's heading, else its incoming one's; an isolated point none.
        seg_valid = (valid[:, :, :-1] & valid[:, :, 1:])[..., None]
        none = jnp.zeros_like(unit[:, :, :1])
        out_dir = jnp.concatenate([jnp.where(seg_valid, unit, 0.0), none], 2)
        in_dir = jnp.concatenate([none, jnp.where(seg_valid, unit, 0.0)], 2)
        has_out = jnp.concatenate([seg_valid, jnp.zeros_like(seg_valid[:, :, :1])], 2)
        vert_dir = jnp.where(has_out, out_dir, in_dir).reshape((B, -1, 2))
        values = jnp.concatenate([jnp.ones(pts.shape[:-1] + (1,)), jnp.concatenate([seg_dir, vert_dir], 1)], -1)
        raster = jnp.zeros((B * hw + 1, 3), jnp.float32).at[flat.reshape(-1)].set(values.reshape(-1, 3),
                                                                                   mode="drop")
        return raster[:-1].reshape(lead + (size, size, 3))
    # uint8 scatter: ~1.7x faster than float32 on CPU (it is memory bound).
    raster = jnp.zeros((B * hw,), jnp.uint8).at[flat.reshape(-1)].set(jnp.uint8(1), mode="drop")
    return raster.reshape(lead + (size, size)).astype(jnp.float32)
