"""Writes the conformance scenes (`scenes.npz` beside this file): small hand-built scenarios on which the official
WOSAC code (`run_official.py`, in its own environment) and `gpd_jax.metrics.realism` under `rules="official"` are
compared (`tests/test_realism_conformance.py`).

    python tests/conformance/make_scenes.py     # in the project's environment; deterministic (seeded)

Seven scenes, 91 frames at 10 Hz (11 history frames, the official current index 10), 6 agents, 4 rollouts each:
a straight two-lane road (rollouts that drift off it and collide), agents that leave the log, appear in it late,
have a gap in their history or their future, and rollouts that lose agents (NaN where they do); open curved road
edges with headings across +-pi; a roundabout whose edges are closed rings (its island a hole with corners);
pedestrians among vehicles (time to collision scores vehicles only); parked cars overlapping in the log; traffic
lights at a junction (red runs in the log and in rollouts, a crossing on green, a stop at red, caution, arrow,
flashing and unknown states, a signal on a lane no agent uses, an agent that leaves the log, a pedestrian on red,
an agent 6 m beside its lane crossing the stop line on red).

Arrays (S scenes, K rollouts, T = 91 frames, F = 80 future frames, A agents, E edges of P points):
  log_xy f32[S, T, A, 2], log_heading f32[S, T, A], log_valid bool[S, T, A] (invalid states hold zeros, as
  stores do); size f32[S, A, 2] (length, width); agent_type i32[S, A] (`gpd_jax.scene.AGENT_TYPES`);
  evaluated bool[S, A];
  sim_xy f32[S, K, F, A, 2], sim_heading f32[S, K, F, A], sim_valid bool[S, K, F, A]: the rollouts' future
  frames as a model hands them over (NaN where an agent is missing; the history is the log's);
  sub_xy f32[S, K, F, A, 2], sub_heading f32[S, K, F, A]: the same with every agent present at every future
  frame (`gpd_jax.metrics.realism.continue_missing`): what the official code is given;
  polygons f32[S, G, V, 2], polygon_valid bool[S, G, V]: the drivable area (even-odd rings);
  edges f32[S, E, P, 2], edge_valid bool[S, E, P]: road edges with the road on their left (closed ones repeat
  their first point); names: the scenes' names;
  lanes f32[S, L, P, 2], lane_valid bool[S, L, P], signal_state i32[S, T, N], signal_stop f32[S, N, 2],
  signal_lane f32[S, N, Q, 2], signal_lane_valid bool[S, N, Q]: lane centrelines and traffic signals as a store
  holds them (`Scene.polylines`, `Scene.signals`; none in a scene without signals), and what the official code
  is handed of them (`gpd_jax.metrics.realism.official_signal_arrays`): official_lanes f32[S, R, W, 2],
  official_lane_valid bool[S, R, W], signal_row i32[S, N], signal_present bool[S, N].
"""

from __future__ import annotations

import pathlib

import jax.numpy as jnp
import numpy as np

from gpd_jax.data.signals import LANE_POINTS, lane_piece
from gpd_jax.geometry import SIGNAL_STATE_ID, RoadGeometry, TrafficSignals
from gpd_jax.metrics.realism import continue_missing, official_signal_arrays, orient_edges
from gpd_jax.scene import TYPE_ID

T, H, A, K = 91, 11, 6, 4
F = T - H
DT = 0.1
OUT = pathlib.Path(__file__).with_name("scenes.npz")


def along(path: np.ndarray, s: np.ndarray):
    """Positions and headings at arc lengths `s [...]` along the polyline `path [N, 2]`."""
    seg = np.diff(path, axis=0)
    cum = np.concatenate([[0.0], np.cumsum(np.linalg.norm(seg, axis=1))])
    x, y = np.interp(s, cum, path[:, 0]), np.interp(s, cum, path[:, 1])
    i = np.clip(np.searchsorted(cum, s, side="right") - 1, 0, len(seg) - 1)
    return np.stack([x, y], -1), np.arctan2(seg[i, 1], seg[i, 0])


def drive(path, s0, v0, accel, t=T):
    """Arc length of an agent that starts at s0 with speed v0 and a per-frame acceleration profile."""
    a = np.broadcast_to(np.asarray(accel, float), (t,))
    v = np.maximum(v0 + np.cumsum(a) * DT, 0.0)
    s = s0 + np.concatenate([[0.0], np.cumsum(v[:-1]) * DT])
    return along(path, s)


def arc(cx, cy, r, a0, a1, n):
    a = np.linspace(a0, a1, n)
    return np.stack([cx + r * np.cos(a), cy + r * np.sin(a)], -1)


def rect(x0, y0, x1, y1):
    return np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]], float)


class Scene:
    def __init__(self, name):
        self.name = name
        self.xy = np.zeros((T, A, 2))
        self.h = np.zeros((T, A))
        self.valid = np.zeros((T, A), bool)
        self.size = np.tile([[4.6, 1.9]], (A, 1))
        self.type = np.full(A, TYPE_ID["car"])
        self.type[0] = TYPE_ID["ego"]
        self.evaluated = np.zeros(A, bool)
        self.polygons, self.edges = [], []
        self.lanes, self.signals = [], []  # lane centrelines; (stop point, controlled lane, states i32[T])

    def agent(self, i, xy, h, frames=slice(None)):
        self.xy[frames, i], self.h[frames, i], self.valid[frames, i] = xy[frames], h[frames], True


def rollouts(scene: Scene, rng, noise=0.04, turn=0.004):
    """K rollouts of the log's future with drifting noise (positions and headings), missing where the log is."""
    xy = np.repeat(scene.xy[None, H:], K, 0).copy()
    h = np.repeat(scene.h[None, H:], K, 0).copy()
    xy += np.cumsum(rng.normal(0, noise, xy.shape), axis=1)
    h += np.cumsum(rng.normal(0, turn, h.shape), axis=1)
    valid = np.repeat(scene.valid[None, H:], K, 0).copy()
    valid &= scene.valid[H - 1][None, None]
    return xy, h, valid


def straight_road(scene: Scene, x0=-120.0, x1=420.0, half=4.0):
    scene.polygons.append(rect(x0, -half, x1, half))
    ring = rect(x0, -half, x1, half)
    scene.edges.append(np.concatenate([ring, ring[:1]]))  # closed, counter-clockwise: the road on the left


def scene_straight(rng):
    s = Scene("straight_road")
    straight_road(s)
    lanes = [np.array([[-120, y], [420, y]], float) for y in (-1.75, 1.75)]
    for i in range(A):
        xy, h = drive(lanes[i % 2], 10.0 + 9.0 * (i // 2) + 3 * (i % 2), 9 + i % 3,
                      0.6 * np.sin(np.arange(T) / (7 + i)))
        s.agent(i, xy, h)
    s.evaluated[:5] = True
    xy, h, v = rollouts(s, rng)
    xy[1, 10:, 2, 1] += np.cumsum(np.full(F - 10, 0.12))  # drifts off the road
    xy[2, 5:, 1, 0] += np.cumsum(np.linspace(0, 0.5, F - 5))  # runs into the car ahead in its lane
    xy[3, 30:, 4, :] = xy[3, 30, 4, :]  # stops dead
    return s, xy, h, v


def scene_leaving(rng):
    s = Scene("agents_leave")
    straight_road(s)
    lanes = [np.array([[-120, y], [420, y]], float) for y in (-1.75, 1.75)]
    for i in range(A):
        xy, h = drive(lanes[i % 2], 5.0 + 12.0 * i, 8 + (i % 3), 0.3 * np.cos(np.arange(T) / 9))
        s.agent(i, xy, h)
    s.valid[H + 41:, 2] = False  # leaves the log
    s.valid[:20, 3] = False  # appears after the current frame: in neither the rollouts nor the log
    s.valid[:4, 4] = s.valid[H - 2, 4] = False  # gaps in its history
    s.valid[H + 30:H + 35, 1] = False  # a gap in its future
    s.xy[~s.valid], s.h[~s.valid] = 0.0, 0.0  # stores hold zeros where an agent is missing
    s.evaluated[[0, 1, 2, 3, 4]] = True  # 3 is dropped: not valid at the current frame
    xy, h, v = rollouts(s, rng)
    v[:2, 50:, 5] = False  # the model loses an agent
    v[2, 20:, 2] = False
    v[3, 70:, 0] = False
    xy[~v], h[~v] = np.nan, np.nan
    return s, xy, h, v


def scene_curved(rng):
    s = Scene("curved_road_open_edges")
    a0, a1 = -0.6 * np.pi, 0.85 * np.pi  # headings cross +-pi along the way
    outer, inner = arc(0, 0, 38, a0, a1, 60), arc(0, 0, 30, a1, a0, 50)
    s.polygons.append(np.concatenate([outer, inner]))
    s.edges += [outer, inner]  # open: counter-clockwise outside, clockwise inside (the road on the left)
    for i in range(A):
        r = 32.0 if i % 2 else 36.0
        path = arc(0, 0, r, a0, a1, 200)
        xy, h = drive(path, 4.0 + 8.0 * (i // 2) + 2 * (i % 2), 7 + 0.5 * i, 0.4 * np.sin(np.arange(T) / 5 + i))
        s.agent(i, xy, h)
    s.evaluated[[0, 2, 3, 4, 5]] = True
    xy, h, v = rollouts(s, rng, noise=0.06)
    xy[0, 20:, 2] *= (1 + np.linspace(0, 0.15, F - 20))[:, None]  # drifts out of the bend
    xy[2, 20:, 5] *= (1 - np.linspace(0, 0.2, F - 20))[:, None]  # drifts into the inside
    return s, xy, h, v


def scene_roundabout(rng):
    s = Scene("roundabout_closed_edges")
    outer = arc(0, 0, 25, 0, 2 * np.pi, 25)[:-1]
    island = arc(0, 0, 12, 2 * np.pi, 0, 9)[:-1]  # an octagon, clockwise: a hole
    s.polygons += [outer, island]
    s.edges += [np.concatenate([outer, outer[:1]]), np.concatenate([island, island[:1]])]
    for i in range(A):
        r = 15.0 if i % 2 else 21.0
        path = arc(0, 0, r, i * 1.0, i * 1.0 + 2.5 * np.pi, 300)
        xy, h = drive(path, 0.0, 5 + 0.4 * i, 0.2 * np.cos(np.arange(T) / 4 + i))
        s.agent(i, xy, h)
    s.evaluated[:] = True
    xy, h, v = rollouts(s, rng, noise=0.05, turn=0.01)
    xy[1, 10:, 1] *= (1 - np.linspace(0, 0.45, F - 10))[:, None]  # cuts through the island
    xy[3, 10:, 0] *= (1 + np.linspace(0, 0.3, F - 10))[:, None]  # leaves the roundabout
    return s, xy, h, v


def scene_pedestrians(rng):
    s = Scene("pedestrians_and_vehicles")
    straight_road(s, half=6.0)
    for i in range(A):
        ped = i in (2, 4)  # two pedestrians on the verge, the second catching up with the first
        y = 4.8 if ped else (-1.75 if i % 2 else 1.75)
        path = np.array([[-120, y], [420, y]], float)
        s0 = {2: 40.3, 4: 33.1}.get(i, 20.0 + 10 * i)  # no distance lands on a bin edge (float noise would pick a bin)
        xy, h = drive(path, s0, {2: 1.17, 4: 2.43}.get(i, 6 + i), 0.0)
        s.agent(i, xy, h)
        if ped:
            s.size[i], s.type[i] = (0.6, 0.6), TYPE_ID["other"]
    s.type[5] = TYPE_ID["bus"]
    s.size[5] = (12.0, 2.5)
    s.evaluated[1:] = True
    xy, h, v = rollouts(s, rng)
    xy[1, :, 3, 0] += np.cumsum(np.full(F, 0.25))  # closes in on the car ahead
    return s, xy, h, v


def scene_parked(rng):
    s = Scene("parked_overlapping")
    straight_road(s, half=8.0)
    spots = [(0.0, -6.0, 0.0), (4.0, -6.2, 0.05), (30.0, 6.0, np.pi), (33.5, 5.8, -np.pi + 0.02)]
    for i, (x, y, hd) in enumerate(spots):
        s.agent(i + 2, np.tile([[x, y]], (T, 1)), np.full(T, hd))
    for i in range(2):
        path = np.array([[-60, 1.75 - 3.5 * i], [420, 1.75 - 3.5 * i]], float)
        xy, h = drive(path, 20.0 * i, 3.0 + i, np.where(np.arange(T) < 40, 1.0, -0.8))
        s.agent(i, xy, h)
    s.evaluated[:] = True
    xy, h, v = rollouts(s, rng, noise=0.02, turn=0.002)
    xy[:, :, 2:] = s.xy[None, H:, 2:]  # parked cars stay put in most rollouts
    h[:, :, 2:] = s.h[None, H:, 2:]
    xy[0, 30:, 3, 0] += 1.5  # one jumps (a glitch in a rollout)
    return s, xy, h, v


def scene_traffic_lights(rng):
    s = Scene("traffic_lights")
    s.polygons.append(rect(-120, -60, 120, 60))
    ring = rect(-120, -60, 120, 60)
    s.edges.append(np.concatenate([ring, ring[:1]]))

    def line(p0, p1, step):  # a lane centreline, points `step` apart with the last one at p1
        n = int(np.ceil(np.linalg.norm(np.subtract(p1, p0)) / step))
        return np.linspace(p0, p1, n + 1)

    east0, east1 = line((-110, -1.75), (110.3, -1.75), 2.7), line((-109, 1.75), (111, 1.75), 2.3)
    north, west = line((8.0, -58), (8.0, 59), 3.1), line((110, 5.25), (-110, 5.25), 2.9)
    s.lanes += [east0, east1, north, west]
    state = lambda *runs: np.concatenate([np.full(n, SIGNAL_STATE_ID[k]) for k, n in runs])  # noqa: E731
    s.signals += [((0.0, -1.75), east0, state(("unknown", 5), ("go", 25), ("caution", 10), ("stop", 51))),
                  ((0.0, 1.75), east1, state(("go", 91))),
                  ((8.0, -12.0), north, state(("arrow_go", 30), ("arrow_caution", 8), ("arrow_stop", 32),
                                              ("flashing_stop", 10), ("stop", 11))),
                  ((12.0, 5.25), west, state(("stop", 91)))]  # no agent uses this lane
    lane_of = {0: east0, 1: east1, 2: east0, 3: north, 4: east0, 5: east0}
    start = {0: (-42.0, 8.0, 0.0), 1: (-40.0, 10.0, 0.0), 3: (-50.0, 9.0, 0.1), 4: (-22.0, 7.0, 0.0),
             5: (-10.0, 1.4, 0.0)}  # x (y for agent 3) at frame 0, speed, acceleration
    for i, (s0, v0, acc) in start.items():
        off = 110.0 if lane_of[i] is not north else 58.0  # the lanes start at x = -110, y = -58
        xy, h = drive(lane_of[i], s0 + off, v0, acc)
        s.agent(i, xy, h)
    # agent 2 behind agent 0 stops at the red light, 3 m short of the stop point
    v = np.concatenate([np.full(40, 8.0), np.maximum(8.0 - 0.16 * np.arange(1, 52), 0.0)])
    x = np.minimum(-60.0 + np.concatenate([[0.0], np.cumsum(v[:-1]) * DT]), -3.0)
    s.agent(2, np.stack([x, np.full(T, -1.75)], -1), np.zeros(T))
    s.xy[:, 5, 1] = -3.2  # a pedestrian beside the lane (nearest to it): crosses on red, not scored
    s.type[5], s.size[5] = TYPE_ID["other"], (0.6, 0.6)
    s.valid[H + 50:, 4] = False  # crossed on yellow, then leaves the log
    s.xy[~s.valid], s.h[~s.valid] = 0.0, 0.0
    s.evaluated[:] = True
    xy, h, v = rollouts(s, rng, noise=0.03, turn=0.002)
    xy[0, :, 0, 0] = np.minimum(xy[0, :, 0, 0], -2.0)  # agent 0 stops before the line
    xy[:2, :, 5, 0] = np.minimum(xy[:2, :, 5, 0], -1.0)  # so does the pedestrian, in two rollouts
    xy[0, :, 3, 0] -= np.linspace(0, 16.0, F)  # agent 3 drifts off its lane: 6 m from the stop point, on red
    xy[1, 45:, 2, 0] = xy[1, 44, 2, 0] + 0.8 * np.arange(1, F - 44)  # agent 2 goes over it on red
    xy[2, :, 3, 1] += np.linspace(0, 30.0, F)  # agent 3 goes early, on the caution arrow
    xy[3, :, 1, 1] -= np.linspace(0, 4.0, F)  # agent 1 drifts to the line between the lanes while it crosses
    xy[3, :, 0, 1] += np.linspace(0, 3.4, F)  # agent 0 too, from the other side, on red
    return s, xy, h, v


SCENES = (scene_straight, scene_leaving, scene_curved, scene_roundabout, scene_pedestrians, scene_parked,
          scene_traffic_lights)


def road_of(scene: Scene) -> RoadGeometry:
    polys, pvalid = pad_rows(scene.polygons, max(len(p) for p in scene.polygons))
    edges, evalid = pad_rows(scene.edges, max(len(e) for e in scene.edges))
    return RoadGeometry(polygons=polys, polygon_valid=pvalid, polygon_kind=np.zeros(len(polys), np.int32),
                        edges=edges, edge_valid=evalid, lanes=np.zeros((1, 2, 2), np.float32),
                        lane_valid=np.zeros((1, 2), bool))


def pad_rows(rows, n):
    out = np.zeros((len(rows), n, 2), np.float32)
    valid = np.zeros((len(rows), n), bool)
    for i, r in enumerate(rows):
        out[i, :len(r)], valid[i, :len(r)] = r, True
    return out, valid


def check_oriented(road: RoadGeometry):
    """The edges as written already have the road on their left (the project's orientation flips none and drops
    none), so both implementations are handed the same lines."""
    e = orient_edges(road)
    a = np.asarray(road.edges)[:, :-1].reshape(-1, 2)
    ok = (np.asarray(road.edge_valid)[:, :-1] & np.asarray(road.edge_valid)[:, 1:]).reshape(-1)
    assert np.array_equal(np.asarray(e.ok), ok), "orient_edges dropped a segment of a conformance scene"
    assert np.allclose(np.asarray(e.a)[ok], a[ok]), "orient_edges flipped an edge of a conformance scene"


def main():
    rng = np.random.default_rng(68)
    built = [make(rng) for make in SCENES]
    roads = [road_of(s) for s, *_ in built]
    for r in roads:
        check_oriented(r)
    g = max(r.polygons.shape[0] for r in roads)
    v = max(r.polygons.shape[1] for r in roads)
    e = max(r.edges.shape[0] for r in roads)
    p = max(r.edges.shape[1] for r in roads)

    def stack_road(field, shape, dtype):
        out = np.zeros((len(roads),) + shape, dtype)
        for i, r in enumerate(roads):
            x = np.asarray(getattr(r, field))
            out[(i,) + tuple(slice(0, n) for n in x.shape)] = x
        return out

    def submission(s, xy, h, v):  # the log's history, then the rollouts; every agent at every future frame
        full = lambda log, sim: np.concatenate([np.repeat(log[None, :H], K, 0), sim], 1)  # noqa: E731
        fx, fh = continue_missing(jnp.asarray(full(s.xy, xy)), jnp.asarray(full(s.h, h)),
                                  jnp.asarray(full(s.valid, v)), H)
        return np.asarray(fx)[:, H:], np.asarray(fh)[:, H:]

    sub = [submission(*b) for b in built]
    for (s, xy, h, vv), (sx, sh) in zip(built, sub):
        # every simulated agent (valid at the current frame) is present at every future frame of the submission
        present = s.valid[H - 1]
        assert np.isfinite(np.asarray(sx)[:, :, present]).all() and np.isfinite(np.asarray(sh)[:, :, present]).all()
    f32 = np.float32
    # lanes and traffic signals (scenes without any hold none; the official code is then handed none)
    ln = max(1, max(len(sc.lanes) for sc, *_ in built))
    lp = max([2] + [len(q) for sc, *_ in built for q in sc.lanes])
    ns = max(1, max(len(sc.signals) for sc, *_ in built))
    lanes, lane_valid = np.zeros((len(built), ln, lp, 2), f32), np.zeros((len(built), ln, lp), bool)
    sig_state = np.zeros((len(built), T, ns), np.int32)
    sig_stop = np.zeros((len(built), ns, 2), f32)
    sig_lane = np.zeros((len(built), ns, LANE_POINTS, 2), f32)
    sig_lane_valid = np.zeros((len(built), ns, LANE_POINTS), bool)
    for i, (sc, *_) in enumerate(built):
        for j, q in enumerate(sc.lanes):
            lanes[i, j, :len(q)], lane_valid[i, j, :len(q)] = q, True
        for j, (stop, lane, states) in enumerate(sc.signals):
            piece = lane_piece(lane, np.asarray(stop, float))  # what a store holds (`gpd_jax.data.signals`)
            sig_state[i, :, j], sig_stop[i, j] = states, stop
            sig_lane[i, j, :len(piece)], sig_lane_valid[i, j, :len(piece)] = piece, True
    signals = TrafficSignals(state=sig_state, stop=sig_stop, lane=sig_lane, lane_valid=sig_lane_valid)
    handed = official_signal_arrays(signals, lanes, lane_valid)  # what the official code is given
    np.savez_compressed(
        OUT, names=np.array([s.name for s, *_ in built]),
        log_xy=np.stack([s.xy for s, *_ in built]).astype(f32),
        log_heading=np.stack([s.h for s, *_ in built]).astype(f32),
        log_valid=np.stack([s.valid for s, *_ in built]),
        size=np.stack([s.size for s, *_ in built]).astype(f32),
        agent_type=np.stack([s.type for s, *_ in built]).astype(np.int32),
        is_vehicle=np.stack([s.type != TYPE_ID["other"] for s, *_ in built]),
        evaluated=np.stack([s.evaluated & s.valid[H - 1] for s, *_ in built]),
        sim_xy=np.stack([b[1] for b in built]).astype(f32), sim_heading=np.stack([b[2] for b in built]).astype(f32),
        sim_valid=np.stack([b[3] for b in built]),
        sub_xy=np.stack([np.asarray(x) for x, _ in sub]).astype(f32),
        sub_heading=np.stack([np.asarray(x) for _, x in sub]).astype(f32),
        polygons=stack_road("polygons", (g, v, 2), f32), polygon_valid=stack_road("polygon_valid", (g, v), bool),
        edges=stack_road("edges", (e, p, 2), f32), edge_valid=stack_road("edge_valid", (e, p), bool),
        lanes=lanes, lane_valid=lane_valid, signal_state=sig_state, signal_stop=sig_stop, signal_lane=sig_lane,
        signal_lane_valid=sig_lane_valid, **handed)
    print(f"wrote {OUT} ({OUT.stat().st_size / 1e3:.0f} kB, {len(built)} scenes)")


if __name__ == "__main__":
    main()
