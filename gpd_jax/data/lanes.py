"""SLEDGE vector lanes of a frame, in numpy: polylines + the frame's ego pose -> f32[50, 20, 2], bool[50].

The rules (SLEDGE `process_lines`, without its training-time pose noise):

1. express the polylines in the frame's ego frame (x forward, y left);
2. resample every polyline at 0.25 m of arc length (from its first point; its last point kept);
3. keep the points with |x| <= 32 and |y| <= 32;
4. split each line into maximal runs of consecutive kept points; drop runs of fewer than 3 points;
5. sort the runs by their minimum distance to the ego (the origin) and keep the 50 nearest;
6. resample each run to 20 points evenly spaced in arc length, end points included.

Output slots are ordered nearest first; absent slots are zeros with `valid` False. Values are metres,
not normalized. Rigid transforms commute with arc-length resampling, so step 2 is done once per sample in
the scene frame and steps 3-6 per frame (`vector_lanes_frames` handles all frames of a sample at once).
"""

from __future__ import annotations

import numpy as np

from gpd_jax.data.preprocess import to_frame

NUM_LINES = 50
NUM_POINTS = 20
STEP = 0.25
HALF = 32.0
MIN_RUN = 3


def _resample_all(polylines: np.ndarray, valid: np.ndarray, step: float) -> tuple[np.ndarray, np.ndarray]:
    """Resamples every valid polyline at `step` m -> (points f64[R, 2], line index i64[R])."""
    pts, ids = [], []
    for i in range(polylines.shape[0]):
        p = np.asarray(polylines[i][valid[i]], np.float64)
        if len(p) < 2:
            continue
        seg = np.linalg.norm(np.diff(p, axis=0), axis=-1)
        keep = np.concatenate([[True], seg > 1e-9])
        p = p[keep]
        if len(p) < 2:
            continue
        s = np.concatenate([[0.0], np.cumsum(seg[seg > 1e-9])])
        t = np.arange(0.0, s[-1], step)
        if s[-1] - t[-1] > 1e-6:
            t = np.append(t, s[-1])
        pts.append(np.stack([np.interp(t, s, p[:, 0]), np.interp(t, s, p[:, 1])], -1))
        ids.append(np.full(len(t), i, np.int64))
    if not pts:
        return np.zeros((0, 2)), np.zeros((0,), np.int64)
    return np.concatenate(pts), np.concatenate(ids)


def vector_lanes_frames(polylines: np.ndarray, valid: np.ndarray, poses: np.ndarray,
                        num_lines: int = NUM_LINES, num_points: int = NUM_POINTS, step: float = STEP,
                        half: float = HALF, min_run: int = MIN_RUN) -> tuple[np.ndarray, np.ndarray]:
    """Vector lanes of every frame of one sample.

    Args:
      polylines: f32[L, P, 2] lane centrelines in the scene frame.
      valid: bool[L, P] which points exist.
      poses: f32[T, 3] ego pose (x, y, heading) of each frame in the scene frame.
    Returns:
      (lanes f32[T, num_lines, num_points, 2] in each frame's ego frame, lanes_valid bool[T, num_lines]).
    """
    pts, line = _resample_all(np.asarray(polylines), np.asarray(valid, bool), step)
    return _frame_lanes(pts, line, poses, num_lines, num_points, half, min_run)


def _frame_lanes(pts: np.ndarray, line: np.ndarray, poses: np.ndarray, num_lines: int, num_points: int,
                 half: float, min_run: int) -> tuple[np.ndarray, np.ndarray]:
    """Steps 3-6 for resampled points f64[R, 2] in the scene frame, `line` i64[R] the polyline of each (equal
    ids on consecutive points = one line), at every pose f32[T, 3] -> as `vector_lanes_frames`."""
    poses = np.asarray(poses, np.float64)
    T = poses.shape[0]
    out = np.zeros((T, num_lines, num_points, 2), np.float32)
    out_valid = np.zeros((T, num_lines), bool)
    R = len(pts)
    if R == 0 or T == 0:
        return out, out_valid
    q = to_frame(pts[None, :, :], poses[:, None, :])  # [T, R, 2]
    inside = np.all(np.abs(q) <= half, axis=-1)  # [T, R]
    # run starts: inside, and the previous point (same frame) is outside or on another line
    prev_in = np.concatenate([np.zeros((T, 1), bool), inside[:, :-1]], 1)
    same_line = np.concatenate([[False], line[1:] == line[:-1]])
    start = inside & ~(prev_in & same_line[None])
    ft, fr = np.nonzero(inside)  # frame-major, point order within a frame
    if len(ft) == 0:
        return out, out_valid
    run_id = np.cumsum(start[ft, fr]) - 1  # one id per (frame, run)
    n_runs = int(run_id[-1]) + 1
    counts = np.bincount(run_id, minlength=n_runs)
    first = np.concatenate([[0], np.cumsum(counts)[:-1]])
    run_frame = ft[first]
    d = np.linalg.norm(q[ft, fr], axis=-1)
    run_dist = np.minimum.reduceat(d, first)
    good = counts >= min_run
    # rank runs within their frame by distance, keep the nearest num_lines
    order = np.lexsort((run_dist, run_frame))
    order = order[good[order]]
    fr_sorted = run_frame[order]
    starts_of_frame = np.searchsorted(fr_sorted, np.arange(T))
    rank = np.arange(len(order)) - starts_of_frame[fr_sorted]
    keep = rank < num_lines
    sel, sel_rank, sel_frame = order[keep], rank[keep], fr_sorted[keep]
    if len(sel) == 0:
        return out, out_valid
    # arc length within each run, offset by a run-specific constant so one np.interp serves all runs
    xy = q[ft, fr]
    step_len = np.linalg.norm(np.diff(xy, axis=0), axis=-1)
    cum = np.concatenate([[0.0], np.cumsum(step_len)])
    s = cum - cum[first[run_id]]  # arc length from the run's first point
    run_len = s[first + counts - 1]
    big = float(run_len.max()) + 1.0
    key = s + run_id * big
    # targets: only for the selected runs
    frac = np.linspace(0.0, 1.0, num_points)
    tgt = (sel[:, None] * big + run_len[sel][:, None] * frac[None, :])  # [S, num_points]
    # restrict the interpolation table to the selected runs' points
    mask = np.isin(run_id, sel)
    kx, px, py = key[mask], xy[mask, 0], xy[mask, 1]
    ix = np.interp(tgt.ravel(), kx, px).reshape(tgt.shape)
    iy = np.interp(tgt.ravel(), kx, py).reshape(tgt.shape)
    out[sel_frame, sel_rank] = np.stack([ix, iy], -1).astype(np.float32)
    out_valid[sel_frame, sel_rank] = True
    return out, out_valid


def vector_lanes_carried(polylines: np.ndarray, valid: np.ndarray, from_pose: np.ndarray, poses: np.ndarray,
                         num_lines: int = NUM_LINES, num_points: int = NUM_POINTS, step: float = STEP,
                         half: float = HALF, min_run: int = MIN_RUN) -> tuple[np.ndarray, np.ndarray]:
    """The lanes visible at `from_pose`, seen from each of `poses`: a map that persists but never extends.

    The polylines are resampled at `step`, cut to the runs inside the window of `from_pose` (|x|, |y| <= half in
    its ego frame), and those runs go through the steps 3-6 of `vector_lanes_frames` at `poses` (cropped to each
    frame's window, nearest 50, 20 points each). Lanes that enter a later frame's window from outside the first one are absent:
    with the logged poses this is the map-persistence baseline of `gpd_jax.evaluate`, the map analogue of
    constant velocity. At `poses == from_pose` the result equals `vector_lanes_frames` up to float rounding.

    Args:
      polylines f32[L, P, 2], valid bool[L, P] (scene frame); from_pose f32[3]; poses f32[T, 3].
    Returns:
      (f32[T, num_lines, num_points, 2], bool[T, num_lines]) as `vector_lanes_frames`.
    """
    pts, line = _resample_all(np.asarray(polylines), np.asarray(valid, bool), step)
    inside = np.all(np.abs(to_frame(pts, np.asarray(from_pose, np.float64))) <= half, axis=-1)
    # a new line id wherever the line changes or the point enters the window; the points inside kept
    start = inside & ~np.concatenate([[False], inside[:-1] & (line[1:] == line[:-1])])
    run = np.cumsum(start) - 1
    return _frame_lanes(pts[inside], run[inside], poses, num_lines, num_points, half, min_run)


def vector_lanes(polylines: np.ndarray, valid: np.ndarray, pose: np.ndarray, **kw) -> tuple[np.ndarray, np.ndarray]:
    """One frame: polylines f32[L, P, 2], valid bool[L, P], pose f32[3] -> (f32[50, 20, 2], bool[50])."""
    lanes, ok = vector_lanes_frames(polylines, valid, np.asarray(pose)[None], **kw)
    return lanes[0], ok[0]


def vector_lanes_batch(polylines: np.ndarray, valid: np.ndarray, poses: np.ndarray, **kw
                       ) -> tuple[np.ndarray, np.ndarray]:
    """Batched over samples: f32[B, L, P, 2], bool[B, L, P], f32[B, T, 3] -> f32[B, T, 50, 20, 2], bool[B, T, 50]."""
    res = [vector_lanes_frames(p, v, q, **kw) for p, v, q in zip(polylines, valid, poses)]
    return np.stack([r[0] for r in res]), np.stack([r[1] for r in res])
