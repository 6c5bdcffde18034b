"""The lanes an evaluation scores generated maps against: ground-truth and persistence lanes of the scored frames
(host numpy). Map tokens are encoded and decoded by the map tokenizer (`MapTokenizer.encode_frames`,
`MapTokenizer.decode_tokens`)."""

from __future__ import annotations

import numpy as np

from gpd_jax.data.lanes import vector_lanes_carried, vector_lanes_frames
from gpd_jax.spec import ModelSpec


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
