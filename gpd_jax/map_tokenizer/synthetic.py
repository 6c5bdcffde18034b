"""Hand-built lane maps for tests and smoke runs (never for reported results).

Each sample is a few circular-arc lanes drawn inside the 64 x 64 m window of a random ego pose, sampled every
1 m in the scene frame (as the data store's polylines), with the matching vector targets: each lane resampled
to `num_points` points by arc length in the ego frame (SLEDGE's `linspace(0, L, 20)`).
"""

from __future__ import annotations

import numpy as np


def resample(line: np.ndarray, n: int) -> np.ndarray:
    """f64[n, 2] points evenly spaced by arc length along `line: f[P, 2]` (endpoints included)."""
    seg = np.linalg.norm(np.diff(line, axis=0), axis=-1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    t = np.linspace(0.0, s[-1], n)
    return np.stack([np.interp(t, s, line[:, 0]), np.interp(t, s, line[:, 1])], -1)


def synthetic_lanes(seed: int, batch: int, max_lines: int = 24, max_points: int = 64, num_lines_out: int = 50,
                    num_points: int = 20, half: float = 31.0) -> dict[str, np.ndarray]:
    """A batch of random lane maps.

    Returns a dict of numpy arrays:
      polylines f32[B, L, P, 2] (scene frame), polyline_valid bool[B, L, P], pose f32[B, 3],
      lanes f32[B, num_lines_out, num_points, 2] (ego frame), lanes_valid bool[B, num_lines_out].
    """
    rng = np.random.default_rng(seed)
    polylines = np.zeros((batch, max_lines, max_points, 2), np.float32)
    pvalid = np.zeros((batch, max_lines, max_points), bool)
    lanes = np.zeros((batch, num_lines_out, num_points, 2), np.float32)
    lvalid = np.zeros((batch, num_lines_out), bool)
    pose = np.zeros((batch, 3), np.float32)
    for b in range(batch):
        pose[b] = (rng.uniform(-50, 50), rng.uniform(-50, 50), rng.uniform(-np.pi, np.pi))
        c, s = np.cos(pose[b, 2]), np.sin(pose[b, 2])
        n_lines = rng.integers(2, min(max_lines, num_lines_out) + 1)
        k = 0
        for _ in range(n_lines):
            p = rng.uniform(-half + 4, half - 4, 2)
            h = rng.uniform(-np.pi, np.pi)
            curv = rng.choice([0.0, rng.uniform(-0.08, 0.08)])
            length = int(rng.integers(8, max_points))
            pts = [p.copy()]
            for _ in range(length - 1):
                h += curv
                p = p + np.array([np.cos(h), np.sin(h)])
                if np.any(np.abs(p) > half):
                    break
                pts.append(p.copy())
            if len(pts) < 4:
                continue
            ego = np.asarray(pts)
            scene = np.stack([pose[b, 0] + c * ego[:, 0] - s * ego[:, 1],
                              pose[b, 1] + s * ego[:, 0] + c * ego[:, 1]], -1)
            polylines[b, k, :len(pts)] = scene
            pvalid[b, k, :len(pts)] = True
            lanes[b, k] = resample(ego, num_points)
            lvalid[b, k] = True
            k += 1
    return dict(polylines=polylines, polyline_valid=pvalid, pose=pose, lanes=lanes, lanes_valid=lvalid)
