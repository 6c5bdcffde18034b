"""RawLog -> fixed-shape samples (pure numpy; shared by the SUMO and nuPlan sources).

A *sample* is a dict of numpy arrays for one 101-frame window (see `SAMPLE_SPEC` for keys, dtypes,
shapes). Conventions, as in `gpd_jax.scene`:

* scene frame = ego frame of the current frame `c = num_history - 1` (index 20): the ego box centre at
  frame c is the origin, its heading is zero, x forward, y left;
* slot 0 is the ego; slots 1..A-1 are the nearest vehicles (box-centre distance to the ego centre at frame
  c, at most `agent_radius` metres, valid at frame c), in order of distance, tracked by id through all
  frames with a validity mask; unused slots are invalid with size 0 and type "other";
* `ego_pose[t]` = (x, y, heading) of the ego at frame t in the scene frame: the pose whose frame the map
  of frame t is expressed in;
* the map is stored as raw lane centrelines in the scene frame, resampled every `lane_spacing` (1 m) and
  clipped to what the ego's 64 x 64 m window (plus a small margin) sees in any of the 101 frames:
  `polylines f32[L, P, 2]` with `polyline_valid bool[L, P]` (a polyline's valid points are a prefix).
  Rasters (`gpd_jax.map_tokenizer.raster.rasterize(polylines, polyline_valid, ego_pose[t])`) and SLEDGE
  vector lanes (`gpd_jax.data.lanes.vector_lanes_frames`) are derived from these deterministically.

Sizes (paper configuration): T=101, A=33, L=`max_lines`=96 polylines of P=`max_line_points`=128
points, float32 (about 98 kB of lanes per sample; on generated SUMO networks a sample uses a median of
25 and at most ~64 polylines, ~1000 points in all). A clipped run longer than P points is split into chunks sharing their end points; if more than
L runs are visible the L nearest to the ego's path are kept; both are counted in the build statistics.

Bad input never produces a sample silently: a window whose ego has non-finite or out-of-range
coordinates is skipped and counted; agent-frames with non-finite values or |x| or |y| >= `max_coord`
(the agent tokenizer's range, 300 m) are marked invalid and counted.
"""

from __future__ import annotations

import dataclasses
from collections import Counter
from typing import Iterator

import numpy as np

from gpd_jax.data.errors import DataError
from gpd_jax.data.boxes import sample_has_overlap
from gpd_jax.data.raw import RawLog
from gpd_jax.data.roadgeom import RoadIndex, clip_road
from gpd_jax.data.signals import clip_signals, signal_spec
from gpd_jax.scene import TYPE_ID


@dataclasses.dataclass(frozen=True)
class SampleConfig:
    num_history: int = 21
    num_future: int = 80
    num_agents: int = 33  # ego + 32 nearest vehicles
    agent_radius: float = 80.0  # metres from the ego centre at the current frame
    max_coord: float = 300.0  # |x|, |y| must stay strictly below this in the scene frame
    view_half: float = 32.0  # half side of the ego's map window
    view_margin: float = 1.5  # extra clip margin so that the resampled lines reach the window border
    lane_spacing: float = 1.0
    max_lines: int = 96
    max_line_points: int = 128
    min_neighbours: int = 0  # SUMO ego choice: vehicles within agent_radius at the current frame
    min_ego_travel: float = 0.0  # SUMO ego choice: metres the ego's centre moves over the window
    window_stride: int = 10  # frames between windows for logs with a fixed ego (nuPlan)
    reject_overlaps: bool = False  # skip windows in which two recorded boxes overlap (SUMO quality gate)
    max_road_rings: int = 64  # drivable-area rings per sample (G)
    max_ring_vertices: int = 32  # vertices per ring (V)
    max_road_edges: int = 64  # road-edge runs per sample (E)
    max_edge_points: int = 32  # points per road-edge run (P_e)
    road_tolerance: float = 0.1  # metres: simplification of area rings and edges

    @property
    def num_frames(self) -> int:
        return self.num_history + self.num_future

    @property
    def current(self) -> int:
        return self.num_history - 1


def sample_spec(cfg: SampleConfig = SampleConfig()) -> dict[str, tuple[tuple[int, ...], str]]:
    """Key -> (shape, dtype) of one sample."""
    T, A, L, P = cfg.num_frames, cfg.num_agents, cfg.max_lines, cfg.max_line_points
    return {
        "xy": ((T, A, 2), "float32"),
        "heading": ((T, A), "float32"),
        "valid": ((T, A), "bool"),
        "size": ((A, 2), "float32"),
        "agent_type": ((A,), "int8"),
        "ego_pose": ((T, 3), "float32"),
        "polylines": ((L, P, 2), "float32"),
        "polyline_valid": ((L, P), "bool"),
        "road_polygons": ((cfg.max_road_rings, cfg.max_ring_vertices, 2), "float32"),
        "road_polygon_valid": ((cfg.max_road_rings, cfg.max_ring_vertices), "bool"),
        "road_polygon_kind": ((cfg.max_road_rings,), "int8"),
        "road_edges": ((cfg.max_road_edges, cfg.max_edge_points, 2), "float32"),
        "road_edge_valid": ((cfg.max_road_edges, cfg.max_edge_points), "bool"),
        "road_map_edges": ((cfg.max_road_edges, cfg.max_edge_points, 2), "float32"),
        "road_map_edge_valid": ((cfg.max_road_edges, cfg.max_edge_points), "bool"),
        "road_edge_source": ((), "int8"),
        **signal_spec(T),
    }


SAMPLE_SPEC = sample_spec()


def wrap(a):
    return (np.asarray(a) + np.pi) % (2 * np.pi) - np.pi


def to_frame(xy: np.ndarray, pose: np.ndarray) -> np.ndarray:
    """World points `f[..., 2]` -> the frame of `pose = f[..., 3]` (x, y, heading); leading dims broadcast."""
    xy, pose = np.asarray(xy), np.asarray(pose)
    dx, dy = xy[..., 0] - pose[..., 0], xy[..., 1] - pose[..., 1]
    c, s = np.cos(pose[..., 2]), np.sin(pose[..., 2])
    return np.stack([c * dx + s * dy, -s * dx + c * dy], -1)


def resample_polyline(pts: np.ndarray, spacing: float) -> np.ndarray:
    """f[P, 2] -> points every `spacing` metres of arc length from the start, plus the end point."""
    pts = np.asarray(pts, np.float64)
    seg = np.linalg.norm(np.diff(pts, axis=0), axis=-1)
    keep = np.concatenate([[True], seg > 1e-9])
    pts, s = pts[keep], np.concatenate([[0.0], np.cumsum(seg[seg > 1e-9])])
    if len(pts) < 2:
        return pts
    t = np.arange(0.0, s[-1], spacing)
    if s[-1] - t[-1] > 1e-6:
        t = np.append(t, s[-1])
    return np.stack([np.interp(t, s, pts[:, 0]), np.interp(t, s, pts[:, 1])], -1)


@dataclasses.dataclass(frozen=True)
class LanePoints:
    """All lane centrelines of a log resampled once: `xy f64[M, 2]`, `line f32[M]` (polyline index)."""

    xy: np.ndarray
    line: np.ndarray


def lane_points(lanes, spacing: float = 1.0) -> LanePoints:
    parts = [resample_polyline(p, spacing) for p in lanes if len(p) >= 2]
    parts = [p for p in parts if len(p) >= 2]
    if not parts:
        return LanePoints(np.zeros((0, 2)), np.zeros((0,), np.int32))
    return LanePoints(np.concatenate(parts), np.concatenate([np.full(len(p), i, np.int32)
                                                             for i, p in enumerate(parts)]))


def clip_lanes(lp: LanePoints, scene_pose_world: np.ndarray, ego_pose: np.ndarray, cfg: SampleConfig,
               stats: Counter | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Lane points visible from the ego window in any frame, as padded polylines in the scene frame.

    Args:
      lp: the log's resampled lane points (world frame).
      scene_pose_world: f[3] the scene frame's pose in the world.
      ego_pose: f[T, 3] ego pose per frame in the scene frame.
    Returns:
      (polylines f32[L, P, 2], polyline_valid bool[L, P]).
    """
    L, P = cfg.max_lines, cfg.max_line_points
    out = np.zeros((L, P, 2), np.float32)
    ok = np.zeros((L, P), bool)
    if len(lp.xy) == 0:
        return out, ok
    half = cfg.view_half + cfg.view_margin
    reach = half * np.sqrt(2.0)
    pts = to_frame(lp.xy, scene_pose_world)
    lo, hi = ego_pose[:, :2].min(0) - reach, ego_pose[:, :2].max(0) + reach
    near = np.nonzero(np.all((pts >= lo) & (pts <= hi), axis=-1))[0]
    vis = np.zeros(len(pts), bool)
    if len(near):
        q = pts[near]
        d = q[None, :, :] - ego_pose[:, None, :2]  # [T, m, 2]
        c, s = np.cos(ego_pose[:, 2])[:, None], np.sin(ego_pose[:, 2])[:, None]
        u = c * d[..., 0] + s * d[..., 1]
        v = -s * d[..., 0] + c * d[..., 1]
        vis[near] = np.any((np.abs(u) <= half) & (np.abs(v) <= half), axis=0)
    idx = np.nonzero(vis)[0]
    if len(idx) == 0:
        return out, ok
    brk = np.nonzero((np.diff(idx) != 1) | (np.diff(lp.line[idx]) != 0))[0] + 1
    runs = [r for r in np.split(idx, brk) if len(r) >= 2]
    chunks = []
    for r in runs:
        if len(r) <= P:
            chunks.append(r)
        else:
            if stats is not None:
                stats["lane_runs_chunked"] += 1
            for a in range(0, len(r) - 1, P - 1):
                c_ = r[a:a + P]
                if len(c_) >= 2:
                    chunks.append(c_)
    if len(chunks) > L:
        if stats is not None:
            stats["lane_chunks_dropped"] += len(chunks) - L
        # keep the chunks nearest to the ego path
        path = ego_pose[:, :2]
        dist = [np.min(np.linalg.norm(pts[c_][:, None, :] - path[None, ::5], axis=-1)) for c_ in chunks]
        chunks = [chunks[i] for i in np.argsort(dist, kind="stable")[:L]]
    for i, c_ in enumerate(chunks):
        out[i, :len(c_)] = pts[c_]
        ok[i, :len(c_)] = True
    return out, ok


def road_index(log: RawLog, cfg: SampleConfig = SampleConfig()) -> RoadIndex | None:
    """The log's drivable areas and map road edges merged for `clip_road` (None when the log has neither)."""
    if not log.areas and not log.road_edges:
        return None
    return RoadIndex(log.areas, cfg.road_tolerance, edge_lines=log.road_edges, edge_source=log.areas_outline)


def make_sample(log: RawLog, start: int, ego: int, cfg: SampleConfig = SampleConfig(),
                lp: LanePoints | None = None, stats: Counter | None = None, road: RoadIndex | None = None
                ) -> dict[str, np.ndarray] | None:
    """One sample from frames [start, start + T) of `log` with track `ego` as the ego (None if skipped).

    `lp` / `road`: the log's `lane_points` / `road_index`, made once per log by callers that cut many windows
    (computed here when not given).

    Skips (and counts in `stats`) windows where the ego is not valid throughout or has bad coordinates.
    """
    stats = Counter() if stats is None else stats
    T, A, c = cfg.num_frames, cfg.num_agents, cfg.current
    w = slice(start, start + T)
    if start < 0 or start + T > log.num_frames:
        raise ValueError(f"window [{start}, {start + T}) outside log {log.name} of {log.num_frames} frames")
    ev = log.agent_valid[w, ego]
    exy, eh = log.agent_xy[w, ego], log.agent_heading[w, ego]
    if not ev.all():
        stats["skip_ego_not_present"] += 1
        return None
    if not (np.isfinite(exy).all() and np.isfinite(eh).all()):
        stats["skip_ego_nonfinite"] += 1
        return None
    origin = np.array([exy[c, 0], exy[c, 1], eh[c]])
    # neighbours at the current frame
    vc = log.agent_valid[start + c].copy()
    vc[ego] = False
    pc = log.agent_xy[start + c]
    dist = np.linalg.norm(pc - origin[:2], axis=-1)
    cand = np.nonzero(vc & np.isfinite(dist) & (dist <= cfg.agent_radius))[0]
    cand = cand[np.argsort(dist[cand], kind="stable")][: A - 1]
    ids = np.concatenate([[ego], cand]).astype(np.int64)
    k = len(ids)
    xy = np.zeros((T, A, 2), np.float32)
    hd = np.zeros((T, A), np.float32)
    valid = np.zeros((T, A), bool)
    size = np.zeros((A, 2), np.float32)
    atype = np.full((A,), TYPE_ID["other"], np.int8)
    sxy = to_frame(log.agent_xy[w][:, ids], origin)  # [T, k, 2]
    shd = wrap(log.agent_heading[w][:, ids] - origin[2])
    v = log.agent_valid[w][:, ids].copy()
    finite = np.isfinite(sxy).all(-1) & np.isfinite(shd)
    stats["agent_frames_nonfinite"] += int(np.sum(v & ~finite))
    v &= finite
    inrange = np.all(np.abs(np.nan_to_num(sxy, nan=0.0)) < cfg.max_coord, axis=-1)
    if not inrange[:, 0].all():
        stats["skip_ego_out_of_range"] += 1
        return None
    stats["agent_frames_out_of_range"] += int(np.sum(v & ~inrange))
    v &= inrange
    xy[:, :k] = np.where(v[..., None], sxy, 0.0)
    hd[:, :k] = np.where(v, shd, 0.0)
    valid[:, :k] = v
    size[:k] = log.agent_size[ids]
    atype[:k] = log.agent_type[ids]
    atype[0] = TYPE_ID["ego"]
    ego_pose = np.concatenate([xy[:, 0], hd[:, 0:1]], -1).astype(np.float32)
    if lp is None:
        lp = lane_points(log.lanes, cfg.lane_spacing)
    poly, pvalid = clip_lanes(lp, origin, ego_pose.astype(np.float64), cfg, stats)
    if road is None and (log.areas or log.road_edges):
        road = road_index(log, cfg)
    geo = clip_road(road, origin, ego_pose.astype(np.float64), reach=(cfg.view_half + cfg.view_margin) * np.sqrt(2.0),
                    G=cfg.max_road_rings, V=cfg.max_ring_vertices, E=cfg.max_road_edges, P=cfg.max_edge_points,
                    tolerance=cfg.road_tolerance, stats=stats, agents_xy=xy[valid].astype(np.float64))
    if road is None:
        stats["samples_without_road_geometry"] += 1
    agents = xy[valid].astype(np.float64)
    sig = clip_signals(log.signals, w, lambda p: to_frame(p, origin), agents.min(0) - 10.0, agents.max(0) + 10.0,
                       ego_pose[:, :2].astype(np.float64), stats)
    if log.signals is not None and not (sig["signal_state"] != 0).any():
        stats["samples_without_signal_states"] += 1
    stats["samples"] += 1
    return {"xy": xy, "heading": hd, "valid": valid, "size": size, "agent_type": atype, "ego_pose": ego_pose,
            "polylines": poly, "polyline_valid": pvalid, **geo, **sig}


def sample_windows(log: RawLog, cfg: SampleConfig, num: int | None, rng: np.random.Generator
                   ) -> list[tuple[int, int]]:
    """(start frame, ego track) pairs for a log.

    With a fixed ego (`log.ego_index`, nuPlan): every `window_stride` frames. Otherwise (SUMO): `num`
    distinct random pairs of a window start and an ego present throughout with at least `min_neighbours`
    vehicles within `agent_radius` at the current frame, the egos drawn with probability proportional to
    their neighbour count (busier scenes), starts spread uniformly.
    """
    T, c = cfg.num_frames, cfg.current
    F = log.num_frames
    if F < T:
        return []
    if log.ego_index is not None:
        starts = list(range(0, F - T + 1, cfg.window_stride))
        out = [(s, int(log.ego_index)) for s in starts]
        if num is not None and len(out) > num:
            keep = np.sort(rng.choice(len(out), num, replace=False))
            out = [out[i] for i in keep]
        return out
    num = 1 if num is None else num
    starts = rng.permutation(F - T + 1)
    out: list[tuple[int, int]] = []
    used: set[tuple[int, int]] = set()
    # present throughout: cumulative valid counts
    cv = np.concatenate([np.zeros((1, log.num_agents), np.int64), np.cumsum(log.agent_valid, 0)], 0)
    per_start = max(1, int(np.ceil(num / max(1, len(starts)))))
    for s in starts:
        if len(out) >= num:
            break
        present = (cv[s + T] - cv[s]) == T
        cand = np.nonzero(present)[0]
        if len(cand) == 0:
            continue
        if len(cand) > 16:  # score a random subset of the candidates only (cheap on big networks)
            cand = rng.choice(cand, 16, replace=False)
        pc = log.agent_xy[s + c]
        others = pc[log.agent_valid[s + c]]
        d = np.linalg.norm(pc[cand][:, None] - others[None], axis=-1)
        nb = np.sum(d <= cfg.agent_radius, axis=1) - 1
        travel = np.linalg.norm(log.agent_xy[s + T - 1, cand] - log.agent_xy[s, cand], axis=-1)
        ok = (nb >= cfg.min_neighbours) & (travel >= cfg.min_ego_travel)
        cand, nb = cand[ok], nb[ok]
        if len(cand) == 0:
            continue
        p = (nb + 1.0) / np.sum(nb + 1.0)
        for e in rng.choice(cand, size=min(per_start, len(cand)), replace=False, p=p):
            if (int(s), int(e)) not in used:
                used.add((int(s), int(e)))
                out.append((int(s), int(e)))
    return out[:num]


def check_rawlog(log: RawLog) -> None:
    """Raises `DataError` (naming the log) if the arrays of a RawLog disagree in shape or are empty."""
    F, N = np.shape(log.agent_xy)[:2] if np.ndim(log.agent_xy) == 3 else (None, None)
    problems = []
    if F is None or np.shape(log.agent_xy)[2] != 2:
        problems.append(f"agent_xy shape {np.shape(log.agent_xy)} is not [F, N, 2]")
    else:
        for name, want in (("agent_heading", (F, N)), ("agent_valid", (F, N)), ("agent_size", (N, 2)),
                           ("agent_type", (N,)), ("timestamps", (F,))):
            if np.shape(getattr(log, name)) != want:
                problems.append(f"{name} shape {np.shape(getattr(log, name))}, expected {want}")
        if len(log.agent_ids) != N:
            problems.append(f"{len(log.agent_ids)} agent ids for {N} tracks")
        if N == 0 or F == 0:
            problems.append("empty log (no frames or no tracks)")
        if log.ego_index is not None and not 0 <= log.ego_index < N:
            problems.append(f"ego_index {log.ego_index} out of range")
    if problems:
        raise DataError(log.name, "bad RawLog: " + "; ".join(problems))


def iter_samples(log: RawLog, cfg: SampleConfig = SampleConfig(), num: int | None = None, seed: int = 0,
                 stats: Counter | None = None) -> Iterator[tuple[str, dict[str, np.ndarray]]]:
    """Yields (scenario id, sample) for the windows of `log` (see `sample_windows`).

    Raises `DataError` for a malformed log; too-short logs and unusable windows are skipped and counted.
    """
    check_rawlog(log)
    rng = np.random.default_rng(seed)
    stats = Counter() if stats is None else stats
    if log.num_frames < cfg.num_frames:
        stats["skip_log_too_short"] += 1
        return
    lp = lane_points(log.lanes, cfg.lane_spacing)
    road = road_index(log, cfg)
    # with the overlap gate, draw spare candidate windows so that `num` samples still come out
    want = None if num is None else (3 * num if cfg.reject_overlaps else num)
    made = 0
    for start, ego in sample_windows(log, cfg, want, rng):
        if num is not None and made >= num:
            break
        s = make_sample(log, start, ego, cfg, lp, stats, road)
        if s is None:
            continue
        if cfg.reject_overlaps:
            stats["overlap_gate_checked"] += 1  # with skip_overlapping_boxes: the share the gate removes
        if cfg.reject_overlaps and sample_has_overlap(s["xy"], s["heading"], s["valid"], s["size"]):
            stats["skip_overlapping_boxes"] += 1
            stats["samples"] -= 1
            continue
        made += 1
        yield f"{log.name}/{start}/{log.agent_ids[ego]}", s
