"""Map glue of an evaluation: ground-truth and persistence lanes of the scored frames (host numpy), and jitted
encode / decode with the model's map tokenizer."""

from __future__ import annotations

import functools

import jax
import numpy as np

from gpd_jax.data.lanes import vector_lanes_carried, vector_lanes_frames
from gpd_jax.spec import ModelSpec


@functools.partial(jax.jit, static_argnames=("tok",))
def decode_map_tokens(tok, params, tokens):
    """Vector lanes of map tokens i32[..., M] with the tokenizer `tok`: (f32[..., Q, P, 2], f32[..., Q])."""
    return tok.decode(params, tokens)


@functools.partial(jax.jit, static_argnames=("tok",))
def encode_map_frames(tok, params, polylines, polyline_valid, poses):
    """Map tokens of every pose: polylines f32[B, L, P, 2], bool[B, L, P], poses f32[B, T, 3] -> i32[B, T, M]."""
    return jax.lax.map(lambda a: tok.encode_lanes(params, *a), (polylines, polyline_valid, poses))


def gt_future_lanes(polylines: np.ndarray, polyline_valid: np.ndarray, ego_pose_full: np.ndarray, spec: ModelSpec
                    ) -> tuple[np.ndarray, np.ndarray]:
    """SLEDGE vector lanes of the first max-horizon future model frames of every scenario (host numpy).

    polylines f32[B, L, P, 2], polyline_valid bool[B, L, P], ego_pose_full f32[B, T_stored, 3]
    -> (f32[B, F, 50, 20, 2], bool[B, F, 50]).
    """
    fr = spec.future_stored_frames()
    res = [vector_lanes_frames(p, v, q[fr]) for p, v, q in zip(polylines, polyline_valid, ego_pose_full)]
    return np.stack([r[0] for r in res]), np.stack([r[1] for r in res])


def persistence_future_lanes(polylines: np.ndarray, polyline_valid: np.ndarray, ego_pose_full: np.ndarray,
                             spec: ModelSpec) -> tuple[np.ndarray, np.ndarray]:
    """The `map_persistence` baseline: the lanes visible at the current frame, in each of the frames of
    `gt_future_lanes` (logged ego poses; `gpd_jax.data.lanes.vector_lanes_carried`). Same shapes."""
    fr, cur = spec.future_stored_frames(), spec.full_history - 1
    res = [vector_lanes_carried(p, v, q[cur], q[fr]) for p, v, q in zip(polylines, polyline_valid, ego_pose_full)]
    return np.stack([r[0] for r in res]), np.stack([r[1] for r in res])
