"""SLEDGE vector lanes of a frame, in numpy: polylines + the frame's ego pose -> f32[50, 20, 2], bool[50].

The rules (SLEDGE `process_lines`, without its training-time pose noise):

0. join the chunks the data store cut a long lane run into (`preprocess.clip_lanes`: a polyline of all P
   points continues in the polyline that starts at its last point): they are one lane, and the cut between
   them is an artifact of the store's array width that no raster shows (until 2026-11-26 it was kept, and
   about a third of the frames of generated networks had a lane cut there);
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
    """Resamples every valid polyline at `step` m -> (points f64[R, 2], line index i64[R]); the data store's
    chunks of one run are joined first (rule 0)."""
    if valid.shape[-1] and valid.all(-1).any():
        polylines, valid = recut_polylines(polylines, valid, "join_chunks")
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


def vector_lanes(polylines: np.ndarray, valid: np.ndarray, pose: np.ndarray, recut: str | None = None, **kw
                 ) -> tuple[np.ndarray, np.ndarray]:
    """One frame: polylines f32[L, P, 2], valid bool[L, P], pose f32[3] -> (f32[50, 20, 2], bool[50]).

    `recut` (one of `RECUT_MODES`, or None for the stored cut) re-cuts the polylines first (`recut_polylines`)."""
    if recut:
        polylines, valid = recut_polylines(polylines, valid, recut)
    lanes, ok = vector_lanes_frames(polylines, valid, np.asarray(pose)[None], **kw)
    return lanes[0], ok[0]


def vector_lanes_batch(polylines: np.ndarray, valid: np.ndarray, poses: np.ndarray, **kw
                       ) -> tuple[np.ndarray, np.ndarray]:
    """Batched over samples: f32[B, L, P, 2], bool[B, L, P], f32[B, T, 3] -> f32[B, T, 50, 20, 2], bool[B, T, 50]."""
    res = [vector_lanes_frames(p, v, q, **kw) for p, v, q in zip(polylines, valid, poses)]
    return np.stack([r[0] for r in res]), np.stack([r[1] for r in res])


# ------------------------------------------------------------------------------------------ other cuts of the GT
RECUT_MODES = ("split_mid", "join_chunks", "join_ends", "no_turnarounds")
TURNAROUND_MAX_LENGTH = 30.0  # metres: a stored polyline this short that turns by more than 135 degrees is a U-turn


def _is_turnaround(ln: np.ndarray) -> bool:
    """A short polyline (< TURNAROUND_MAX_LENGTH m) whose end heading is more than 135 degrees from its start's."""
    seg = np.diff(ln, axis=0)
    seg = seg[np.linalg.norm(seg, axis=-1) > 1e-6]
    if len(seg) < 2 or np.linalg.norm(seg, axis=-1).sum() >= TURNAROUND_MAX_LENGTH:
        return False
    a, b = seg[0] / np.linalg.norm(seg[0]), seg[-1] / np.linalg.norm(seg[-1])
    return float(a @ b) < np.cos(np.radians(135.0))


def recut_polylines(polylines: np.ndarray, valid: np.ndarray, mode: str) -> tuple[np.ndarray, np.ndarray]:
    """The same road geometry cut into lines differently (the learnability probe of
    `gpd_jax.map_tokenizer.evaluation.cut_diagnostics`, and the map tokenizer's `data.gt_recut` targets).

    Args:
      polylines: f32[L, P, 2] a sample's stored polylines (valid points a prefix); valid: bool[L, P].
      mode: "split_mid" cuts every polyline of >= 4 points in two at its middle point (both halves keep it);
        "join_chunks" joins only the chunks the data store cut a long run into (`preprocess.clip_lanes`: a
        polyline of all P points whose last point is the next chunk's first), one-to-one as "join_ends";
        "join_ends" joins polylines where one's last point is another's first (within 1 mm) and the pair is
        one-to-one there (the stored chunks of a long lane, chains the network cut at a one-to-one point);
        "no_turnarounds" drops the U-turn connectors (`_is_turnaround`) and then joins as "join_ends": the cut
        a chain merge that ignores SUMO's turnaround connections would give (it changes the geometry by the
        U-turn arcs, so its cut-invariant F1 is below 1).

    Returns:
      (f32[L', P', 2], bool[L', P']) the re-cut polylines, same geometry.
    """
    full = [bool(valid[i].all()) for i in range(polylines.shape[0]) if valid[i].sum() >= 2]
    lines = [np.asarray(polylines[i][valid[i]], np.float64) for i in range(polylines.shape[0]) if valid[i].sum() >= 2]
    if mode == "split_mid":
        out = []
        for ln in lines:
            if len(ln) >= 4:
                k = len(ln) // 2
                out += [ln[:k + 1], ln[k:]]
            else:
                out.append(ln)
    elif mode in ("join_chunks", "join_ends", "no_turnarounds"):
        if mode == "no_turnarounds":
            full = [f for f, ln in zip(full, lines) if not _is_turnaround(ln)]
            lines = [ln for ln in lines if not _is_turnaround(ln)]
        starts = np.array([ln[0] for ln in lines]).reshape(-1, 2)
        ends = np.array([ln[-1] for ln in lines]).reshape(-1, 2)
        close = np.linalg.norm(ends[:, None] - starts[None], axis=-1) < 1e-3  # [i end, j start]
        np.fill_diagonal(close, False)
        if mode == "join_chunks":  # only a polyline of all P points continues: the store's chunks of one run
            close &= np.asarray(full, bool)[:, None]
        nxt = {i: int(np.argmax(close[i])) for i in range(len(lines))
               if close[i].sum() == 1 and close[:, int(np.argmax(close[i]))].sum() == 1}
        has_prev = set(nxt.values())
        out, done = [], set()
        heads = [i for i in range(len(lines)) if i not in has_prev]
        for i in heads + list(range(len(lines))):  # chain heads first, then what is left (pure cycles)
            if i in done:
                continue
            chain, cur = [lines[i]], i
            done.add(i)
            while cur in nxt and nxt[cur] not in done:
                cur = nxt[cur]
                done.add(cur)
                chain.append(lines[cur][1:])
            out.append(np.concatenate(chain))
    else:
        raise ValueError(f"recut mode must be one of {RECUT_MODES}, got {mode!r}")
    p = max(len(ln) for ln in out) + 1 if out else 2  # + 1: no output is full, so never taken for a store chunk
    pts = np.zeros((max(len(out), 1), p, 2), np.float32)
    ok = np.zeros((max(len(out), 1), p), bool)
    for i, ln in enumerate(out):
        pts[i, :len(ln)] = ln
        ok[i, :len(ln)] = True
    return pts, ok
