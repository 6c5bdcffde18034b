"""Oriented-box overlap shared by the preprocessing quality gate, the importers' overlap gates
(`gpd_jax.data.sources`) and the dataset statistics."""

from __future__ import annotations

import numpy as np


def boxes_overlap(xy_a, h_a, size_a, xy_b, h_b, size_b, eps: float = 0.0) -> np.ndarray:
    """Separating-axis test for oriented boxes (broadcast over leading dims).

    xy f[..., 2], h f[...], size f[..., 2] (length, width). True where the boxes overlap by more than
    `eps` metres along every separating axis (touching boxes do not overlap).
    """
    d = np.asarray(xy_b) - np.asarray(xy_a)
    ua = np.stack([np.cos(h_a), np.sin(h_a)], -1)
    va = np.stack([-np.sin(h_a), np.cos(h_a)], -1)
    ub = np.stack([np.cos(h_b), np.sin(h_b)], -1)
    vb = np.stack([-np.sin(h_b), np.cos(h_b)], -1)
    la, wa = np.asarray(size_a)[..., 0] / 2, np.asarray(size_a)[..., 1] / 2
    lb, wb = np.asarray(size_b)[..., 0] / 2, np.asarray(size_b)[..., 1] / 2
    overlap = np.ones(d.shape[:-1], bool)
    for n in (ua, va, ub, vb):
        ra = la * np.abs(np.sum(ua * n, -1)) + wa * np.abs(np.sum(va * n, -1))
        rb = lb * np.abs(np.sum(ub * n, -1)) + wb * np.abs(np.sum(vb * n, -1))
        overlap &= np.abs(np.sum(d * n, -1)) < ra + rb - eps
    return overlap


def sample_has_overlap(xy, heading, valid, size) -> bool:
    """xy f[T, A, 2], heading f[T, A], valid bool[T, A], size f[A, 2] -> any two valid boxes overlap."""
    A = xy.shape[1]
    i, j = np.triu_indices(A, 1)
    both = valid[:, i] & valid[:, j]
    reach = 0.5 * np.linalg.norm(size, axis=-1)
    near = both & (np.linalg.norm(xy[:, i] - xy[:, j], axis=-1) < reach[i] + reach[j])
    t, p = np.nonzero(near)
    if len(t) == 0:
        return False
    ii, jj = i[p], j[p]
    return bool(boxes_overlap(xy[t, ii], heading[t, ii], size[ii], xy[t, jj], heading[t, jj], size[jj]).any())
