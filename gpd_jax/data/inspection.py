"""Dataset statistics (`python -m gpd_jax.data inspect DIR --json PATH`).

Keys: scenarios, scenarios_per_split, agents_per_frame_mean / _max (valid vehicles besides the ego),
lanes_per_frame_mean / _min (SLEDGE vector lanes, `gpd_jax.data.lanes`), stationary_fraction (valid
agent-frames, ego included, under 0.5 m/s), agent_stationary_fraction / ego_stationary_fraction (the same for
the other agents / the ego alone), ego_stationary_at_current_fraction (scenarios whose ego is under 0.5 m/s at
the current frame), agents_stationary_at_current_fraction (other agents valid there, under 0.5 m/s),
agents_never_moving_fraction (other agents valid at the current frame that never reach 0.5 m/s in the window:
parked), stationary_agents_that_go_fraction (of the other agents stationary at the current frame, those that
later move more than 2 m from where they stand), agents_stationary_on_other_area_fraction /
agents_stationary_in_lanes_fraction (other agents at the current frame that stand on a drivable area of kind
"other", such as SUMO's parking strips / elsewhere: in lanes and junctions, queues and stops; samples with road
geometry only), agent_speed_mps_p50 (other agents), speed_mps_p5 / p50 / p95, accel_mps2_p1 / p99 (from finite
differences of consecutive valid frames at 10 Hz), log_collisions (scenarios in which two recorded
oriented boxes overlap in some frame, separating-axis test), frame_rate_floor (`frame_rate_floor_errors`: for
model rates of 1, 2 and 5 Hz, how far the logged future lies from straight lines between the model's frames,
overall and while agents brake or turn), build_wall_s, plus a few extras.

`per_source` repeats the agent figures (scenarios, agents per frame, speeds, ego median speed, stationary
fraction, accelerations, logged overlaps, agent types) for each source, so that simulated (SUMO) and recorded
(nuPlan, ScenarioNet) scenes in one store, or stores of different sources, can be compared. The source of a
shard is its `meta.json` "source" ("sumo", "nuplan", "scenarionet"; the build's source for older shards),
followed by "/<dataset>" where the shard names one (ScenarioNet: "scenarionet/waymo", "scenarionet/nuscenes").
"""

from __future__ import annotations

import functools

import jax
import numpy as np

from gpd_jax.data import lanes as lanes_lib
from gpd_jax.data import store
from gpd_jax.data.boxes import boxes_overlap, sample_has_overlap  # noqa: F401 (re-exported)
from gpd_jax.geometry import AREA_KIND_ID
from gpd_jax.scene import AGENT_TYPES

DT = 0.1
STATIONARY_MPS = 0.5  # speed under which an agent-frame counts as stationary (as `gpd_jax.metrics.agents`)
FLOOR_STRIDES = {"1hz": 10, "2hz": 5, "5hz": 2}  # model frame rates the frame-rate floor is measured for
MANEUVER_ACCEL_MPS2 = 2.0  # |acceleration| over which an agent-frame counts as braking / accelerating hard
MANEUVER_YAW_RATE = 0.2  # |yaw rate| (rad/s) over which an agent-frame counts as turning


def frame_rate_floor_errors(xy: np.ndarray, heading: np.ndarray, valid: np.ndarray, current: int, stride: int
                            ) -> tuple[np.ndarray, np.ndarray]:
    """How far a model at `stride` x the stored period can follow the logged motion of the future frames.

    The log is kept only at the frames current, current + stride, ... (a model's frames); between two kept frames
    the path is their straight line at uniform speed. Returns (errors f64[N] in metres: logged position against
    that line, at every stored frame in between whose agent is valid there and at both kept frames,
    maneuver bool[N]: the agent brakes or accelerates by more than MANEUVER_ACCEL_MPS2 or turns faster than
    MANEUVER_YAW_RATE at that frame). `xy f[B, T, A, 2]`, `heading f[B, T, A]`, `valid bool[B, T, A]`.
    """
    xy = xy.astype(np.float64)
    T = xy.shape[1]
    sp = np.linalg.norm(np.diff(xy, axis=1), axis=-1) / DT  # [B, T-1, A]
    acc = np.zeros(valid.shape)
    acc[:, 1:-1] = np.diff(sp, axis=1) / DT
    yaw = np.zeros(valid.shape)
    yaw[:, 1:] = np.abs(np.angle(np.exp(1j * np.diff(heading.astype(np.float64), axis=1)))) / DT
    ok3 = np.zeros(valid.shape, bool)  # valid at t - 1, t, t + 1: the finite differences are defined
    ok3[:, 1:-1] = valid[:, :-2] & valid[:, 1:-1] & valid[:, 2:]
    hard = ok3 & ((np.abs(acc) > MANEUVER_ACCEL_MPS2) | (yaw > MANEUVER_YAW_RATE))
    errs, man = [], []
    for a in range(current, T - stride, stride):
        b = a + stride
        for i in range(1, stride):
            w = i / stride
            line = (1 - w) * xy[:, a] + w * xy[:, b]
            ok = valid[:, a] & valid[:, b] & valid[:, a + i]
            errs.append(np.linalg.norm(xy[:, a + i] - line, axis=-1)[ok])
            man.append(hard[:, a + i][ok])
    if not errs:
        return np.zeros(0), np.zeros(0, bool)
    return np.concatenate(errs), np.concatenate(man)


def point_in_kind(points: np.ndarray, rings: np.ndarray, ring_valid: np.ndarray, ring_kind: np.ndarray,
                  kind: int) -> np.ndarray:
    """bool[P]: whether `points f[P, 2]` lie in the drivable area of `kind` (even-odd over that kind's rings, as
    `gpd_jax.geometry.area_kinds`). `rings f[G, V, 2]` with `ring_valid bool[G, V]` (a prefix), `ring_kind i[G]`."""
    sel = (np.asarray(ring_kind) == kind) & ring_valid.any(-1)
    if len(points) == 0 or not sel.any():
        return np.zeros(len(points), bool)
    r, ok = rings[sel].astype(np.float64), ring_valid[sel]
    nxt = np.roll(r, -1, axis=1)
    n = ok.sum(-1)  # the closing segment runs from the last valid vertex back to the first
    last = np.arange(r.shape[1])[None] == (n - 1)[:, None]
    nxt = np.where(last[..., None], r[:, :1], nxt)
    a, b = r[None], nxt[None]  # [1, G, V, 2]
    p = np.asarray(points, np.float64)[:, None, None]  # [P, 1, 1, 2]
    straddle = (a[..., 1] > p[..., 1]) != (b[..., 1] > p[..., 1])
    with np.errstate(divide="ignore", invalid="ignore"):
        x = a[..., 0] + (p[..., 1] - a[..., 1]) * (b[..., 0] - a[..., 0]) / (b[..., 1] - a[..., 1])
    cross = straddle & (p[..., 0] < x) & ok[None]
    return cross.sum((-2, -1)) % 2 == 1  # over all rings of the kind: holes are rings too


class _Figures:
    """Accumulates the agent figures of a group of shards (`current`: the current frame index)."""

    def __init__(self, current: int = 20):
        self.current = current
        self.agents, self.speeds, self.ego_speeds, self.accels = [], [], [], []
        self.other_speeds, self.ego_current, self.other_current, self.never_moving = [], [], [], []
        self.still_then_go = []
        self.still_place = np.zeros(3, np.int64)  # agents at the current frame: stationary on "other" areas,
        # stationary elsewhere (lanes, junctions: queues, stops), all (with road geometry)
        self.collisions, self.n = 0, 0
        self.type_hist = np.zeros(len(AGENT_TYPES), np.int64)
        self.floor = {k: ([], []) for k in FLOOR_STRIDES}

    def add(self, a: dict) -> None:
        v = a["valid"]
        self.agents.append(v[:, :, 1:].sum(-1).ravel())
        xy = a["xy"].astype(np.float64)
        ok1 = v[:, 1:] & v[:, :-1]
        sp = np.linalg.norm(np.diff(xy, axis=1), axis=-1) / DT
        self.speeds.append(sp[ok1])
        self.ego_speeds.append(sp[..., 0][ok1[..., 0]])
        self.other_speeds.append(sp[..., 1:][ok1[..., 1:]])
        c = self.current
        if 1 <= c < v.shape[1]:
            okc = ok1[:, c - 1]  # [B, A]: valid at c - 1 and c
            self.ego_current.append(sp[:, c - 1, 0][okc[:, 0]])
            self.other_current.append(sp[:, c - 1, 1:][okc[:, 1:]])
            # agents (not the ego) at the current frame that never reach 0.5 m/s over their valid steps
            fast = np.any(ok1[..., 1:] & (sp[..., 1:] >= STATIONARY_MPS), axis=1)  # [B, A-1]
            has = ok1[..., 1:].any(1) & v[:, c, 1:]
            self.never_moving.append(~fast[has])
            # agents (not the ego) stationary at the current frame: do they later move > 2 m from where they stand?
            still = okc[:, 1:] & (sp[:, c - 1, 1:] < STATIONARY_MPS)  # [B, A-1]
            away = np.linalg.norm(xy[:, c:, 1:] - xy[:, c:c + 1, 1:], axis=-1)  # [B, T-c, A-1]
            moved = np.any(v[:, c:, 1:] & (away > 2.0), axis=1)
            self.still_then_go.append(moved[still])
            if "road_polygons" in a:
                other = AREA_KIND_ID["other"]
                for k in range(len(v)):
                    if not a["road_polygon_valid"][k].any():
                        continue
                    pts = xy[k, c, 1:][still[k]]
                    on = point_in_kind(pts, a["road_polygons"][k], a["road_polygon_valid"][k],
                                       a["road_polygon_kind"][k], other)
                    self.still_place += (int(on.sum()), int((~on).sum()), int(okc[k, 1:].sum()))
        ok2 = ok1[:, 1:] & ok1[:, :-1]
        self.accels.append((np.diff(sp, axis=1) / DT)[ok2])
        for key, stride in FLOOR_STRIDES.items():
            e, m = frame_rate_floor_errors(xy, a["heading"], v, max(c, 0), stride)
            self.floor[key][0].append(e)
            self.floor[key][1].append(m)
        for k in range(len(v)):
            self.collisions += sample_has_overlap(xy[k], a["heading"][k], v[k], a["size"][k])
            present = v[k].any(0)
            self.type_hist += np.bincount(a["agent_type"][k][present].astype(np.int64), minlength=len(AGENT_TYPES))
        self.n += len(v)

    def summary(self) -> dict:
        agents = np.concatenate(self.agents)
        speeds = np.concatenate(self.speeds) if self.speeds else np.zeros(0)
        ego = np.concatenate(self.ego_speeds) if self.ego_speeds else np.zeros(0)
        accels = np.concatenate(self.accels) if self.accels else np.zeros(0)

        def cat(x):
            return np.concatenate(x) if x else np.zeros(0)

        other, ego_c, other_c, never = (cat(self.other_speeds), cat(self.ego_current), cat(self.other_current),
                                        cat(self.never_moving))
        go = cat(self.still_then_go)

        def share(x):
            return float(np.mean(x < STATIONARY_MPS)) if len(x) else None

        def pct(x, q):
            return float(np.percentile(x, q)) if len(x) else None

        return {
            "scenarios": int(self.n),
            "agents_per_frame_mean": float(agents.mean()),
            "agents_per_frame_max": int(agents.max()),
            "agents_per_frame_min": int(agents.min()),
            "stationary_fraction": float(np.mean(speeds < 0.5)) if len(speeds) else None,
            "speed_mps_p5": pct(speeds, 5),
            "speed_mps_p50": pct(speeds, 50),
            "speed_mps_p95": pct(speeds, 95),
            "ego_speed_mps_p50": pct(ego, 50),
            "agent_speed_mps_p50": pct(other, 50),
            "agent_stationary_fraction": share(other),
            "ego_stationary_fraction": share(ego),
            "ego_stationary_at_current_fraction": share(ego_c),
            "agents_stationary_at_current_fraction": share(other_c),
            "agents_never_moving_fraction": float(np.mean(never)) if len(never) else None,
            "stationary_agents_that_go_fraction": float(np.mean(go)) if len(go) else None,
            "agents_stationary_on_other_area_fraction": (float(self.still_place[0] / self.still_place[2])
                                                         if self.still_place[2] else None),
            "agents_stationary_in_lanes_fraction": (float(self.still_place[1] / self.still_place[2])
                                                    if self.still_place[2] else None),
            "accel_mps2_p1": pct(accels, 1),
            "accel_mps2_p99": pct(accels, 99),
            "log_collisions": int(self.collisions),
            "log_collision_fraction": float(self.collisions / self.n),
            "agent_types": {AGENT_TYPES[i]: int(c) for i, c in enumerate(self.type_hist) if c},
            "frame_rate_floor": {k: _floor_summary(cat(e), cat(m)) for k, (e, m) in self.floor.items()},
        }


def _floor_summary(err: np.ndarray, man: np.ndarray) -> dict:
    """Mean / p95 / max of the frame-rate floor errors (metres), overall and on maneuvering agent-frames."""
    def stats(x):
        return {"n": int(len(x)), "mean_m": float(x.mean()) if len(x) else None,
                "p95_m": float(np.percentile(x, 95)) if len(x) else None,
                "max_m": float(x.max()) if len(x) else None}
    return {"all": stats(err), "maneuver": stats(err[man.astype(bool)]),
            "maneuver_share": float(man.mean()) if len(man) else None}


def shard_source(meta: dict, build_source: str | None = None) -> str:
    """The `per_source` key of a shard: its "source" (or the build's), plus "/<dataset>" where it names one."""
    src = str(meta.get("source") or build_source or "unknown")
    ds = meta.get("dataset")
    return f"{src}/{ds}" if ds else src


def inspect(data_dir: str, with_lanes: bool = True) -> dict:
    """Computes the statistics of every split of a dataset (reads shards one by one: flat memory)."""
    try:
        man = store.read_manifest(data_dir)
    except Exception:  # noqa: BLE001 - a dataset without manifest still has statistics
        man = {}
    build = man.get("build", {})
    n_per_split = {}
    lane_counts = []
    current = int(build.get("sample_config", {}).get("num_history", 21)) - 1
    total = _Figures(current)
    per_source: dict[str, _Figures] = {}
    per_layout: dict[str, dict[str, int]] = {}  # SUMO shards: network layout -> split -> samples
    with_tokens = 0
    for split in store.list_splits(data_dir):
        count = 0
        for path in store.list_shards(data_dir, split):
            sh = store.Shard(path)
            a = {k: np.asarray(v) for k, v in sh.arrays.items()}
            count += sh.num_samples
            with_tokens += sh.num_samples if sh.map_tokens is not None else 0
            total.add(a)
            per_source.setdefault(shard_source(sh.meta, build.get("source")), _Figures(current)).add(a)
            if sh.meta.get("layout"):
                row = per_layout.setdefault(sh.meta["layout"], {})
                row[split] = row.get(split, 0) + sh.num_samples
            if with_lanes:
                for k in range(sh.num_samples):
                    _, lv = lanes_lib.vector_lanes_frames(a["polylines"][k], a["polyline_valid"][k], a["ego_pose"][k])
                    lane_counts.append(lv.sum(-1))
        n_per_split[split] = count
    if total.n == 0:
        from gpd_jax.data.errors import DataError
        raise DataError(data_dir, "dataset has no samples")
    fig = total.summary()
    out = {
        "scenarios": fig["scenarios"],
        "scenarios_per_split": n_per_split,
        **{k: v for k, v in fig.items() if k not in ("scenarios", "agent_types")},
        "build_wall_s": build.get("build_wall_s"),
        "build_wall_s_all_invocations": build.get("build_wall_s_all_invocations"),
        "agent_types": fig["agent_types"],
        "samples_with_map_tokens": int(with_tokens),
        "locations_per_split": {s: len({l for sh in v["shards"] for l in sh["locations"]})
                                for s, v in man.get("splits", {}).items()},
        "build_stats": build.get("stats"),
        "per_source": {src: f.summary() for src, f in sorted(per_source.items())},
        "samples_per_layout": dict(sorted(per_layout.items())),
        "overlap_gate": build.get("overlap_gate"),
        "near_duplicates": build.get("near_duplicates"),
        "traffic": build.get("traffic"),
    }
    if with_lanes:
        lc = np.concatenate(lane_counts)
        out.update({"lanes_per_frame_mean": float(lc.mean()), "lanes_per_frame_min": int(lc.min()),
                    "frames_without_lanes": int(np.sum(lc == 0))})
    return out


def road_edge_summary(data_dir: str, batch: int = 32) -> dict:
    """Per split (`inspect --road-edges`): the scenes per road-edge source (`gpd_jax.geometry.edge_source_names`),
    the scenes with traffic-signal states, and the log's own offroad rate: the share of the agents valid at the
    current frame whose box leaves the road in a future frame, by the realism metric's rule
    (`gpd_jax.metrics.realism`), on the edges it reads ("log_offroad_rate") and, for comparison, on the areas'
    boundary that stores of format 1 had ("log_offroad_rate_area_boundary")."""
    import jax.numpy as jnp

    from gpd_jax.data import loader
    from gpd_jax.geometry import edge_source_names
    from gpd_jax.metrics import realism

    try:
        h = int(store.read_manifest(data_dir).get("build", {}).get("sample_config", {}).get("num_history", 21))
    except Exception:  # noqa: BLE001 - a dataset without manifest: the paper's configuration
        h = 21
    out = {}
    for split in store.list_splits(data_dir):
        src = loader.SplitSource(data_dir, split, with_polylines=True)
        if not src.has_road:
            out[split] = {"scenes": len(src), "edge_sources": {"no_road": len(src)}}
            continue
        sources, signals, off, off_old, n = [], 0, 0, 0, 0
        for b0 in range(0, len(src), batch):
            recs = [src[i] for i in range(b0, min(len(src), b0 + batch))]
            scene = loader.to_scene({k: np.stack([r[k] for r in recs]) for k in recs[0]})
            sources += list(edge_source_names(scene.road))
            if scene.signals is not None:
                signals += int(np.sum(np.any(np.asarray(scene.signals.state) != 0, axis=(-1, -2))))
            road = jax.tree.map(jnp.asarray, scene.road)
            args = [jnp.asarray(getattr(scene, k)) for k in ("xy", "heading", "valid", "size")]
            budget = realism.edge_segment_budget(road)
            o, e = (np.asarray(x) for x in _log_offroad(road, *args, num_history=h, budget=budget))
            old = road.replace(map_edges=None, map_edge_valid=None, edge_source=None)
            o2, _ = (np.asarray(x) for x in _log_offroad(old, *args, num_history=h,
                                                         budget=realism.edge_segment_budget(old)))
            off, off_old, n = off + int(o.sum()), off_old + int(o2.sum()), n + int(e.sum())
        names, counts = np.unique(np.asarray(sources, str), return_counts=True)
        out[split] = {"scenes": len(src), "edge_sources": {str(a): int(c) for a, c in zip(names, counts)},
                      "scenes_with_signals": signals, "agents": n,
                      "log_offroad_rate": off / max(n, 1), "log_offroad_rate_area_boundary": off_old / max(n, 1)}
    return out


@functools.partial(jax.jit, static_argnames=("num_history", "budget"))
def _log_offroad(road, xy, heading, valid, size, num_history: int, budget: int):
    """(offroad agents i32[B], agents valid at the current frame i32[B]) of the logs of a batch of scenes."""
    from gpd_jax.metrics import realism

    def one(road, xy, heading, valid, size):
        f = realism.realism_features(xy, heading, valid, size, num_history, 0.1, realism.orient_edges(road, budget))
        ev = valid[num_history - 1]
        return (f.offroad.any(0) & ev).sum(), ev.sum()

    return jax.vmap(one)(road, xy, heading, valid, size)


def format_summary(s: dict) -> str:
    lines = [f"{s['scenarios']} scenarios {s['scenarios_per_split']}"]
    for k in ("agents_per_frame_mean", "agents_per_frame_max", "lanes_per_frame_mean", "lanes_per_frame_min",
              "stationary_fraction", "agent_stationary_fraction", "ego_stationary_fraction",
              "ego_stationary_at_current_fraction", "agents_stationary_at_current_fraction",
              "agents_never_moving_fraction", "stationary_agents_that_go_fraction",
              "agents_stationary_on_other_area_fraction", "agents_stationary_in_lanes_fraction", "speed_mps_p5", "speed_mps_p50", "agent_speed_mps_p50", "speed_mps_p95",
              "accel_mps2_p1", "accel_mps2_p99", "log_collisions", "build_wall_s"):
        v = s.get(k)
        lines.append(f"  {k:38s} {v:.3f}" if isinstance(v, float) else f"  {k:38s} {v}")
    lines.append(f"  agent types              {s['agent_types']}")
    for k, f in (s.get("frame_rate_floor") or {}).items():
        a, m = f["all"], f["maneuver"]
        if a["n"]:
            lines.append(f"  frame-rate floor {k:4s}    mean {a['mean_m']:.3f} m, p95 {a['p95_m']:.3f} m; maneuvers "
                         f"({f['maneuver_share']:.2f} of frames) mean {m['mean_m'] or 0:.3f} m, p95 {m['p95_m'] or 0:.3f} m")
    if s.get("samples_per_layout"):
        lines.append(f"  samples per layout       {s['samples_per_layout']}")
    if s.get("overlap_gate"):
        g = s["overlap_gate"]
        lines.append(f"  windows with overlaps    {g['windows_with_overlaps']} of {g['windows_checked']} "
                     f"({'removed' if g['enabled'] else 'kept'})")
    if s.get("near_duplicates") is not None:
        lines.append(f"  near-duplicate networks  {len(s['near_duplicates'])}")
    for split, r in (s.get("road_edges") or {}).items():
        lines.append(f"  road edges [{split}]      {r['edge_sources']}, "
                     f"scenes with signals {r.get('scenes_with_signals')}"
                     + (f"; log offroad rate {r['log_offroad_rate']:.4f} (format-1 area boundary "
                        f"{r['log_offroad_rate_area_boundary']:.4f}) over {r['agents']} agents"
                        if "log_offroad_rate" in r else ""))
    for src, f in s.get("per_source", {}).items():
        lines.append(f"  [{src}] {f['scenarios']} scenarios")
        for k in ("agents_per_frame_mean", "agents_per_frame_max", "stationary_fraction", "agent_stationary_fraction",
                  "ego_stationary_at_current_fraction", "agents_stationary_at_current_fraction",
                  "agents_never_moving_fraction", "speed_mps_p50", "agent_speed_mps_p50", "speed_mps_p95",
                  "ego_speed_mps_p50", "accel_mps2_p1", "accel_mps2_p99", "log_collisions", "log_collision_fraction"):
            v = f.get(k)
            lines.append(f"    {k:36s} {v:.3f}" if isinstance(v, float) else f"    {k:36s} {v}")
    return "\n".join(lines)
