"""Traffic-light states of a log and their fixed-shape per-sample arrays (numpy, build time only).

A source that knows its signals (SUMO's signal programs as simulated, ScenarioNet's `dynamic_map_states`,
nuPlan's `traffic_light_status`) gives `RawLog.signals`, a `RawSignals` in the world frame: per controlled lane
its stop point, the lane's centreline around it and the state in every frame, in WOSAC's lane-state enum
(`gpd_jax.geometry.SIGNAL_STATES`: 0 unknown, 4 stop, 6 go, ...). `clip_signals` cuts one sample's arrays
(`SIGNAL_KEYS`, the scene frame):

    signal_state       i8[T, S]       the state of each signal slot in each frame (0 = unknown / no signal)
    signal_stop        f32[S, 2]      the stop point where a vehicle must stop when the state says stop
    signal_lane        f32[S, Q, 2]   the controlled lane around the stop point, in driving order: from
                                      `LANE_BEFORE_M` before the stop point to `LANE_AFTER_M` after it (1 m
                                      spacing, clipped to the lane; Q = 16)
    signal_lane_valid  bool[S, Q]     which lane points exist (a prefix); a slot without points is empty

The S signal slots (32) hold the signals whose stop point lies in the sample's region (the box around the
agents' positions) and that have a known state in a frame of the window, nearest to the ego's path first;
`signals_dropped` counts the rest. What the realism metric does with them: `gpd_jax.metrics.traffic_lights`.
"""

from __future__ import annotations

import dataclasses
from collections import Counter

import numpy as np

SIGNAL_KEYS = ("signal_state", "signal_stop", "signal_lane", "signal_lane_valid")
MAX_SIGNALS = 32  # S
LANE_POINTS = 16  # Q
LANE_BEFORE_M = 8.0
LANE_AFTER_M = 7.0


@dataclasses.dataclass(frozen=True)
class RawSignals:
    """A log's traffic signals in the world frame.

    Attributes:
      stop: f64[N, 2] stop point of each controlled lane.
      lane: tuple of N f64[P_i, 2] the controlled lane's centreline (driving order) through or up to its stop
        point; only the part around the stop point is kept (`lane_piece`).
      state: i8[F, N] the state per frame of the log (`gpd_jax.geometry.SIGNAL_STATES` index; 0 unknown).
    """

    stop: np.ndarray
    lane: tuple
    state: np.ndarray

    def __post_init__(self):
        n = len(self.lane)
        if np.shape(self.stop) != (n, 2) or np.ndim(self.state) != 2 or np.shape(self.state)[1] != n:
            raise ValueError(f"RawSignals: stop {np.shape(self.stop)}, {n} lanes, state {np.shape(self.state)} "
                             "disagree (expected stop [N, 2], N lanes, state [F, N])")


def signal_spec(T: int) -> dict[str, tuple[tuple[int, ...], str]]:
    """Key -> (shape, dtype) of one sample's signal arrays."""
    S, Q = MAX_SIGNALS, LANE_POINTS
    return {"signal_state": ((T, S), "int8"), "signal_stop": ((S, 2), "float32"),
            "signal_lane": ((S, Q, 2), "float32"), "signal_lane_valid": ((S, Q), "bool")}


def empty_signal_arrays(T: int) -> dict[str, np.ndarray]:
    return {k: np.zeros(shape, dtype) for k, (shape, dtype) in signal_spec(T).items()}


def lane_piece(lane: np.ndarray, stop: np.ndarray, before: float = LANE_BEFORE_M, after: float = LANE_AFTER_M,
               num: int = LANE_POINTS) -> np.ndarray:
    """The part of `lane f[P, 2]` from `before` metres before the stop point's projection on it to `after` metres
    after, every metre (at most `num` points, clipped to the lane's ends); f64[<= num, 2]."""
    pts = np.asarray(lane, np.float64)
    seg = np.diff(pts, axis=0)
    seg_len = np.linalg.norm(seg, axis=-1)
    keep = seg_len > 1e-9
    if not keep.any():
        return np.zeros((0, 2))
    pts = np.concatenate([pts[:1], pts[1:][keep]])
    seg, seg_len = seg[keep], seg_len[keep]
    s0 = np.concatenate([[0.0], np.cumsum(seg_len)])
    t = np.clip(np.sum((stop - pts[:-1]) * seg, -1) / seg_len ** 2, 0.0, 1.0)
    near = pts[:-1] + t[:, None] * seg
    i = int(np.argmin(np.linalg.norm(near - stop, axis=-1)))
    s_stop = s0[i] + t[i] * seg_len[i]
    s = s_stop + np.arange(-before, after + 1e-9, 1.0)
    s = s[(s >= 0) & (s <= s0[-1])][:num]
    return np.stack([np.interp(s, s0, pts[:, 0]), np.interp(s, s0, pts[:, 1])], -1)


def clip_signals(signals: RawSignals | None, frames: slice, to_scene, lo: np.ndarray, hi: np.ndarray,
                 path: np.ndarray, stats: Counter | None = None) -> dict[str, np.ndarray]:
    """One sample's `SIGNAL_KEYS` arrays.

    Args:
      signals: the log's signals (None: all empty).
      frames: the window's frames of the log.
      to_scene: world points f[K, 2] -> the scene frame.
      lo, hi: f[2] the sample's region in the scene frame (a stop point outside it is not kept).
      path: f[K, 2] the ego's positions in the scene frame (nearest signals first).
    """
    T = frames.stop - frames.start
    out = empty_signal_arrays(T)
    if signals is None or not len(signals.lane):
        return out
    stats = Counter() if stats is None else stats
    state = np.asarray(signals.state[frames])  # [T, N]
    stop = to_scene(np.asarray(signals.stop, np.float64))
    inside = np.all((stop >= lo) & (stop <= hi), -1) & np.any(state != 0, 0)
    cand = np.nonzero(inside)[0]
    dist = np.min(np.linalg.norm(stop[cand, None] - path[None], axis=-1), -1) if len(cand) else np.zeros(0)
    cand = cand[np.argsort(dist, kind="stable")]
    if len(cand) > MAX_SIGNALS:
        stats["signals_dropped"] += len(cand) - MAX_SIGNALS
        cand = cand[:MAX_SIGNALS]
    for s, n in enumerate(cand):
        piece = lane_piece(to_scene(np.asarray(signals.lane[n], np.float64)), stop[n])
        out["signal_state"][:, s] = state[:, n]
        out["signal_stop"][s] = stop[n]
        out["signal_lane"][s, :len(piece)] = piece
        out["signal_lane_valid"][s, :len(piece)] = True
    stats["signals_kept"] += len(cand)
    return out
