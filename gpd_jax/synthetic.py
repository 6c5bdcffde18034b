"""Synthetic scenes with simple, learnable motion, for tests and benchmarks (never for reported results).

Each agent drives a circular arc at constant speed and yaw rate; some slots are empty and some agents enter or
leave the scene. The map tokens of a scene are a fixed random grid that drifts by one cell every few frames.
"""

from __future__ import annotations

import numpy as np

from gpd_jax.scene import TYPE_ID, Scene, wrap_angle


def synthetic_scenes(seed: int, batch: int, num_frames: int, num_history: int, num_agents: int,
                     num_map_tokens: int, codebook_size: int, dt: float = 0.1) -> Scene:
    """A batch of `batch` scenes in the Scene convention (numpy arrays, leading dim `batch`)."""
    rng = np.random.default_rng(seed)
    b, t_len, a = batch, num_frames, num_agents
    t = (np.arange(t_len) - (num_history - 1)) * dt  # 0 at the current frame
    p0 = rng.uniform(-40, 40, (b, a, 2))
    p0[:, 0] = 0.0
    h0 = rng.uniform(-np.pi, np.pi, (b, a))
    h0[:, 0] = 0.0
    speed = rng.uniform(0, 15, (b, a))
    yaw_rate = rng.uniform(-0.15, 0.15, (b, a))
    heading = h0[:, None, :] + yaw_rate[:, None, :] * t[None, :, None]
    # Exact integral of a constant-speed, constant-yaw-rate arc.
    safe = np.where(np.abs(yaw_rate) < 1e-6, 1e-6, yaw_rate)[:, None, :]
    x = p0[:, None, :, 0] + speed[:, None, :] / safe * (np.sin(heading) - np.sin(h0[:, None, :]))
    y = p0[:, None, :, 1] - speed[:, None, :] / safe * (np.cos(heading) - np.cos(h0[:, None, :]))
    xy = np.stack([x, y], -1).astype(np.float32)
    present = rng.uniform(size=(b, a)) < 0.8
    present[:, 0] = True
    enter = rng.integers(-t_len, t_len // 2, (b, a))
    leave = rng.integers(t_len // 2, 2 * t_len, (b, a))
    frames = np.arange(t_len)[None, :, None]
    valid = present[:, None, :] & (frames >= enter[:, None, :]) & (frames < leave[:, None, :])
    valid[:, :, 0] = True
    xy = np.where(valid[..., None], xy, 0.0).astype(np.float32)
    heading = np.where(valid, wrap_angle(heading), 0.0).astype(np.float32)
    grid = rng.integers(0, codebook_size, (b, num_map_tokens))
    shift = (np.arange(t_len) // 5)[None, :, None]
    map_tokens = np.take_along_axis(
        np.repeat(grid[:, None, :], t_len, 1), (np.arange(num_map_tokens)[None, None, :] + shift) % num_map_tokens,
        axis=2).astype(np.int32)
    size = np.stack([rng.uniform(4.0, 5.5, (b, a)), rng.uniform(1.7, 2.1, (b, a))], -1).astype(np.float32)
    agent_type = np.full((b, a), TYPE_ID["car"], np.int32)
    agent_type[:, 0] = TYPE_ID["ego"]
    ego_pose = np.concatenate([xy[:, :, 0, :], heading[:, :, 0:1]], -1)
    return Scene(xy=xy, heading=heading, valid=valid, size=size, agent_type=agent_type, map_tokens=map_tokens,
                 map_valid=np.ones((b, t_len), bool), ego_pose=ego_pose.astype(np.float32))
