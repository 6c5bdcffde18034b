"""How well a rollout respects its prompt's conditions (`gpd_jax.prompts.Prompt`), beside the usual figures.

Per rolled-out scenario (host numpy, model-rate arrays):

* `given_deviation`: the largest distance (m) and heading difference (rad) between a given agent state and the
  rolled-out one, over every slot and frame the prompt takes from its given data (paths, the log until frame k,
  initial trajectories): 0 when the condition holds to float precision;
* `cap_violations`: slot-frames valid although hidden or beyond the agent cap (should be 0), and the largest
  number of valid agents in a generated frame;
* `lane_offroad`: the share of generated agent positions (future frames, slots the prompt does not give) outside
  the drivable area (`offroad_share`: box centres, `gpd_jax.geometry.on_road`; `offroad_corner_share`: boxes with
  a corner outside), and, under its own name, the share farther than half a lane width from every lane
  centreline (`offroad_share_lane_distance`: the distance to the polylines, which needs no area). The drivable
  area is the store's (`Scene.road`) for a prompt on the log's map, and, for a prompt with lanes of its own (a
  hand-drawn road), the area those lanes cover at `LANE_WIDTH_M` (`road_from_lanes`: each lane buffered by half
  the width on either side, the lanes' union). A store's geometry covers a clipped box around the logged ego
  (and agents): positions beyond it are not judged (`offroad_outside_geometry_share`). A store built before
  road geometry was stored has no drivable area: `offroad_share` is then null (NaN) with `offroad_source` saying
  so and naming the rebuild, and `offroad_share_lane_distance` is the figure there is (no error: the other scores
  do not need the area);
* `agent_figures`: beside them, the usual ADE against the log and collision share of the generated agents;
* `lane_map_f1`: map F1 (the paper's, `gpd_jax.metrics.map`) of the lanes decoded from the rollout's map tokens
  of future frames against the given lanes seen from each frame's rolled-out ego (SLEDGE vector lanes,
  `gpd_jax.data.lanes.vector_lanes_frames`).
"""

from __future__ import annotations

import os
from collections import Counter
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from gpd_jax.data.lanes import vector_lanes_frames
from gpd_jax.data.roadgeom import RoadIndex, clip_road, lane_area
from gpd_jax.geometry import RoadGeometry, on_road, road_from_arrays
from gpd_jax.metrics.agents import box_corners, box_overlap_pairwise
from gpd_jax.metrics.map import map_metric_sums, reduce_map_metrics
from gpd_jax.prompts import Prompt

LANE_WIDTH_M = 3.5  # a hand-drawn lane's width: its drivable area (`road_from_lanes`)
LANE_HALF_WIDTH_M = LANE_WIDTH_M / 2  # farther than this from every centreline is off the lanes
# Where `offroad_share`'s drivable area comes from (`lane_offroad`'s "offroad_source").
OFFROAD_SOURCES = {"store": "the store's drivable-area geometry (Scene.road)",
                   "given_lanes": f"the prompt's own lanes, {LANE_WIDTH_M:g} m wide (road_from_lanes)",
                   "none": "none: the store has no drivable-area geometry (built before it was stored; rebuild it "
                           "with `python -m gpd_jax.data build ...`); offroad_share_lane_distance is reported"}


def _np(p: Prompt) -> Prompt:
    return jax.tree.map(np.asarray, p)


def given_mask(prompt: Prompt, num_history: int) -> np.ndarray:
    """bool[T, A] agent slot-frames whose state the rollout must reproduce from the given data: future frames
    taken from it and every history frame, less removed slots."""
    p = _np(prompt)
    m = p.num_map_tokens
    fl = p.from_log[:, m:].copy()
    fl[:num_history] = True
    return fl & ~p.removed()[None]


def given_deviation(out: Any, given_xy: np.ndarray, given_heading: np.ndarray, given_valid: np.ndarray,
                    prompt: Prompt, num_history: int) -> dict[str, float]:
    """Max position (m) / heading (rad) deviation of the rolled-out states from the given ones where the prompt
    gives them (and they are valid), and the share of those slot-frames whose validity differs. `out`: one
    rollout's xy f32[T, A, 2], heading, valid; given_*: the given data (log with the prompt's overrides)."""
    mask = given_mask(prompt, num_history)
    xy, hd, v = np.asarray(out.xy), np.asarray(out.heading), np.asarray(out.valid)
    both = mask & given_valid & v
    d = np.linalg.norm(xy - given_xy, axis=-1)
    dh = np.abs((hd - given_heading + np.pi) % (2 * np.pi) - np.pi)
    return {"max_xy_m": float(d[both].max()) if both.any() else 0.0,
            "max_heading_rad": float(dh[both].max()) if both.any() else 0.0,
            "validity_mismatch": float((v[mask] != given_valid[mask]).mean()) if mask.any() else 0.0,
            "given_slot_frames": int(mask.sum())}


def cap_violations(out: Any, prompt: Prompt, num_history: int) -> dict[str, float]:
    """Slot-frames valid although removed (hidden or beyond the cap), and the most valid slots in a generated
    frame (ego included)."""
    p = _np(prompt)
    v = np.asarray(out.valid)
    removed = p.removed()
    return {"violations": int(v[:, removed].sum()), "max_valid_slots": int(v[num_history:].sum(-1).max()),
            "cap": int(p.max_agents)}


def agent_figures(out: Any, log_xy: np.ndarray, log_valid: np.ndarray, size: np.ndarray, prompt: Prompt,
                  num_history: int) -> dict[str, float]:
    """The usual figures beside the condition scores, for generated agent slot-frames (future frames, not given):
    mean displacement from the log where both are valid ("ade_m", the log being one possible future), and the
    share of generated slots that overlap another valid box in some future frame ("collision_share", the
    paper's definition over the horizon)."""
    gen = ~given_mask(prompt, num_history)
    gen[:num_history] = False
    v = np.asarray(out.valid)
    both = gen & v & np.asarray(log_valid)
    d = np.linalg.norm(np.asarray(out.xy) - np.asarray(log_xy), axis=-1)
    ov = np.asarray(_box_overlap_pairwise(np.asarray(out.xy)[num_history:], np.asarray(out.heading)[num_history:],
                                         np.asarray(size)[None].repeat(v.shape[0] - num_history, 0),
                                         v[num_history:])).any(-1)  # [F, A]
    slots = (gen & v)[num_history:].any(0)
    hit = (ov & (gen & v)[num_history:]).any(0)
    return {"ade_m": float(d[both].mean()) if both.any() else float("nan"),
            "collision_share": float(hit[slots].mean()) if slots.any() else float("nan"),
            "ade_count": int(both.sum()), "generated_slots": int(slots.sum())}


def distance_to_polylines(points: np.ndarray, lanes: np.ndarray, lanes_valid: np.ndarray) -> np.ndarray:
    """Distance f32[N] from points f32[N, 2] to the nearest segment of polylines f32[L, P, 2] (bool[L, P])."""
    a, b = lanes[:, :-1].reshape(-1, 2), lanes[:, 1:].reshape(-1, 2)
    ok = (lanes_valid[:, :-1] & lanes_valid[:, 1:]).reshape(-1)
    a, b = a[ok], b[ok]
    if not len(a):
        return np.full(len(points), np.inf)
    ab = b - a
    den = np.maximum((ab ** 2).sum(-1), 1e-12)
    t = np.clip(((points[:, None] - a[None]) * ab[None]).sum(-1) / den[None], 0.0, 1.0)
    near = a[None] + t[..., None] * ab[None]
    return np.linalg.norm(points[:, None] - near, axis=-1).min(-1)


def road_from_lanes(lanes: np.ndarray, lanes_valid: np.ndarray, width: float = LANE_WIDTH_M, *,
                    num_rings: int = 64, ring_vertices: int = 128, num_edges: int = 64,
                    edge_points: int = 64) -> RoadGeometry:
    """The drivable area of a hand-drawn road: every lane centreline f32[L, P, 2] (valid points bool[L, P], scene
    frame) buffered by `width` / 2 on either side (`gpd_jax.data.roadgeom.lane_area`, ends cut square), the
    union of all lanes (`RoadIndex`), as a `RoadGeometry` of fixed shape (rings [num_rings, ring_vertices], edges
    [num_edges, edge_points]) around the lanes. Raises ValueError when the union needs more rings than
    `num_rings` (never silently smaller)."""
    lanes, lanes_valid = np.asarray(lanes, np.float64), np.asarray(lanes_valid, bool)
    areas = [lane_area(ln[ok], width) for ln, ok in zip(lanes, lanes_valid) if ok.sum() >= 2]
    areas = [x for x in areas if x is not None]
    stats: Counter = Counter()
    # the region: the lanes' points with a margin wider than the road (clip_road grows its box to hold them)
    pts = lanes[lanes_valid] if lanes_valid.any() else np.zeros((1, 2))
    arr = clip_road(RoadIndex(areas, tolerance=0.02) if areas else None, np.zeros(3), np.zeros((1, 3)), reach=0.0,
                    G=num_rings, V=ring_vertices, E=num_edges, P=edge_points, stats=stats, agents_xy=pts,
                    agent_margin=width + 1.0)
    if stats["road_rings_dropped"]:
        raise ValueError(f"road_from_lanes: the lanes' drivable area needs more than {num_rings} rings of "
                         f"{ring_vertices} vertices ({stats['road_rings_dropped']} dropped); raise num_rings")
    arr["road_polygon_kind"] = arr["road_polygon_kind"].astype(np.int32)
    return road_from_arrays(arr, lanes.astype(np.float32), lanes_valid)


_on_road = jax.jit(on_road)
# compiled once per shape (eager, every call of the scores of each scenario and prompt dispatched each op)
_box_corners = jax.jit(box_corners)
_box_overlap_pairwise = jax.jit(box_overlap_pairwise)


def lane_offroad(out: Any, prompt: Prompt, num_history: int, lanes: np.ndarray, lanes_valid: np.ndarray,
                 road: RoadGeometry | None = None, half_width: float = LANE_HALF_WIDTH_M, *,
                 size: np.ndarray | None = None, source: str | None = None) -> dict[str, Any]:
    """Off-road figures of the generated agent positions (future frames, slots not given there).

    Args:
      out: one rollout: xy f32[T, A, 2], heading f32[T, A], valid bool[T, A] (scene frame).
      lanes, lanes_valid: the lane centrelines f32[L, P, 2] / bool[L, P] the agents should keep to (the prompt's
        own or the log's), for the lane-distance figure (and the area when `road` is None and `source` is not
        "none").
      road: the drivable area (the store's `Scene.road`, unbatched). None: the area of `lanes` at twice
        `half_width` (`road_from_lanes`, the rule for a hand-drawn road), unless `source` is "none".
      size: f32[A, 2] box (length, width) per slot for `offroad_corner_share` (default 4.5 x 1.9 m).
      source: a key of `OFFROAD_SOURCES` (default: "store" with a road, "given_lanes" without); "none" reports
        `offroad_share` as NaN (a store without drivable-area geometry).

    Returns:
      {"offroad_share": share of box centres outside the drivable area, "offroad_corner_share": share of boxes
       with a corner outside it, "offroad_source", "offroad_share_lane_distance": share farther than
       `half_width` from every centreline, "mean_lane_distance_m", "positions": how many positions}. With the
      store's geometry, which covers only a box around the logged ego and agents, the two area shares are over
      the positions inside that box (`_within_extent`) and "offroad_outside_geometry_share" says how many were
      beyond it; a hand-drawn road's area is complete (everything else is off the road), so every position is
      judged there.
    """
    source = source or ("store" if road is not None else "given_lanes")
    if source not in OFFROAD_SOURCES:
        raise ValueError(f"source must be one of {tuple(OFFROAD_SOURCES)}, got {source!r}")
    gen = ~given_mask(prompt, num_history)
    gen[:num_history] = False
    sel = gen & np.asarray(out.valid)
    nan = float("nan")
    res: dict[str, Any] = {"offroad_share": nan, "offroad_corner_share": nan, "offroad_source": source,
                           "offroad_share_lane_distance": nan, "mean_lane_distance_m": nan, "positions": 0}
    if not sel.any():
        return res
    xy, hd = np.asarray(out.xy, np.float32), np.asarray(out.heading, np.float32)
    d = distance_to_polylines(xy[sel], np.asarray(lanes), np.asarray(lanes_valid, bool))
    res.update(offroad_share_lane_distance=float((d > half_width).mean()), mean_lane_distance_m=float(d.mean()),
               positions=int(sel.sum()))
    if source == "none":
        return res
    if road is None:
        road = road_from_lanes(lanes, lanes_valid, 2 * half_width)
    box = np.broadcast_to(np.asarray([4.5, 1.9] if size is None else size, np.float32), xy.shape)
    corners = np.asarray(_box_corners(xy, hd, box))  # [T, A, 4, 2]
    pts = np.concatenate([xy[..., None, :], corners], -2)  # [T, A, 5, 2]: centre and corners, every slot-frame
    inside = np.asarray(_on_road(jax.tree.map(jnp.asarray, road), jnp.asarray(pts)))[sel]  # [N, 5]
    judged = np.ones(len(inside), bool)
    if source == "store":
        # a store's geometry covers a region around the logged ego and agents; beyond it nothing is known
        judged = _within_extent(road, xy[sel])
        res["offroad_outside_geometry_share"] = float((~judged).mean())
    if judged.any():
        res.update(offroad_share=float((~inside[judged, 0]).mean()),
                   offroad_corner_share=float((~inside[judged, 1:]).any(-1).mean()))
    return res


def _within_extent(road: RoadGeometry, xy: np.ndarray) -> np.ndarray:
    """bool[N]: points f32[N, 2] inside the axis-aligned box (scene frame) of the road's valid ring vertices: the
    part of the scene a store's clipped geometry describes (stores clip it to such a box)."""
    pv = np.asarray(road.polygon_valid, bool)
    if not pv.any():
        return np.zeros(len(xy), bool)
    v = np.asarray(road.polygons)[pv]
    return np.all((xy >= v.min(0)) & (xy <= v.max(0)), axis=-1)


# compiled once per shape: called eagerly, its lax.map loops were traced and compiled again at every call (tens of
# seconds each on a CPU: most of a prompt evaluation's time)
_map_metric_sums = jax.jit(map_metric_sums, static_argnames=("step_axis",))


def decoded_map_sums(tokenizer, tokens: np.ndarray, gt: np.ndarray, gt_ok: np.ndarray,
                     step_axis: int | None = None) -> dict[str, np.ndarray]:
    """Map-metric sums (`gpd_jax.metrics.map.map_metric_sums`) of tokens i32[..., F, M] decoded with `tokenizer`
    against vector lanes gt f32[..., F, L, P, 2] / gt_ok bool[..., F, L] of the same frames, in one compiled call;
    frames pooled, or kept apart along `step_axis` of the leading dims (as `map_metric_sums`)."""
    pts, logits = tokenizer.decode_tokens(np.asarray(tokens))
    sums = _map_metric_sums(pts, logits, jnp.asarray(gt, jnp.float32), jnp.asarray(gt_ok, bool), step_axis=step_axis)
    return {k: np.asarray(v) for k, v in sums.items()}


def lane_map_sums(tokenizer, out_map_tokens: np.ndarray, ego_poses: np.ndarray, lanes: np.ndarray,
                  lanes_valid: np.ndarray) -> dict[str, np.ndarray]:
    """Map-metric sums (`gpd_jax.metrics.map.map_metric_sums`, frames pooled) of tokens i32[F, M] decoded with
    `tokenizer` against the given lanes (scene frame) seen from the poses f32[F, 3] the tokens were made around.
    Reduce with `reduce_map_metrics` (after adding the sums of several scenarios)."""
    gt, gt_ok = vector_lanes_frames(np.asarray(lanes), np.asarray(lanes_valid, bool), np.asarray(ego_poses))
    return decoded_map_sums(tokenizer, out_map_tokens, gt, gt_ok)


def add_sums(a: dict[str, np.ndarray] | None, b: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    return dict(b) if a is None else {k: a[k] + b[k] for k in a}


def reduce_map(sums: dict[str, np.ndarray] | None) -> dict[str, float]:
    if sums is None:
        return {}
    r = reduce_map_metrics(sums)
    return {k: r[k] for k in ("map_f1", "map_precision", "map_recall", "map_lateral")}


def rollout_poses(out: Any) -> np.ndarray:
    """f32[T, 3] the rolled-out ego pose of every frame."""
    xy, hd = np.asarray(out.xy), np.asarray(out.heading)
    return np.concatenate([xy[:, 0], hd[:, :1]], -1)


# ------------------------------------------------------------------------------------ prompt evaluation (CLI)
def _aggregate(values, fn) -> float:
    """fn over the finite values (NaN when there are none: nothing to score, without numpy's empty-mean warning)."""
    v = np.asarray(values if values else [], np.float64)
    v = v[np.isfinite(v)] if fn in (np.nanmean, np.nanmax) else v
    return float(fn(v)) if v.size else float("nan")



def evaluate_prompts(model, data: str, split: str, prompt_files: dict[str, dict], *, num_scenarios: int | None,
                     batch_size: int = 8, seed: int = 0, render_count: int = 0, render_dir: str | None = None,
                     size_px: int = 320, log=print, options=None, progress: bool = True) -> dict[str, Any]:
    """Rolls out every scenario of a split under every prompt (JSON content by name) plus the unconditioned
    `traffic_simulation` for reference, in one compiled rollout per batch (per-scenario prompts [B, K]), and
    scores each prompt's conditions (module docstring). `options`: a `gpd_jax.RolloutOptions` (default: the
    paper's rollout). Returns {"prompts": {name: scores}, ...}."""
    from gpd_jax.data.loader import SplitSource, to_scene
    from gpd_jax.decoding import rollout_model
    from gpd_jax.options import RolloutOptions
    from gpd_jax.evaluation.render import render_rollout
    from gpd_jax.prompts import prompt_from_json, prompt_from_task, stack_prompts
    from gpd_jax.spec import EvalError

    spec, tok = model.spec, model.tokenizer
    options = RolloutOptions() if options is None else options
    h = spec.num_history
    src = SplitSource(data, split, with_polylines=True)
    n = len(src) if num_scenarios is None else min(int(num_scenarios), len(src))
    if n == 0:
        raise EvalError(f"split {split!r} of {data} has no scenarios")
    names = ["reference_traffic_simulation"] + list(prompt_files)
    sources: dict[str, set] = {k: set() for k in names}
    if not src.has_road:
        log(f"note: {data}/{split} has no drivable-area geometry (built before it was stored), so offroad_share "
            "is null and offroad_share_lane_distance (distance to the lane centrelines) is the off-road figure; "
            "rebuild the store with `python -m gpd_jax.data build ...` for the drivable-area one")
    bs = max(1, min(batch_size, n))
    acc: dict[str, dict[str, list]] = {k: {} for k in names}
    maps: dict[str, Any] = {k: None for k in names}
    rendered = []
    from tqdm import tqdm

    bar = tqdm(total=n, desc=f"compiling the rollout of {len(names)} prompts (the first batch)", unit="scenario",
               dynamic_ncols=True, disable=not progress)
    for b in range(-(-n // bs)):
        idx = list(range(b * bs, min((b + 1) * bs, n)))
        real = len(idx)
        idx += [idx[-1]] * (bs - real)
        recs = [src[i] for i in idx]
        full = to_scene({k: np.stack([r[k] for r in recs]) for k in recs[0]})
        view = model.prepare(full)
        host_view = jax.tree.map(np.asarray, view)  # on the host once per batch, not once per scenario and prompt
        singles = []
        for j in range(bs):
            sc = jax.tree.map(lambda x: x[j], host_view)
            row = [prompt_from_task("traffic_simulation", spec.num_frames, spec.num_map_tokens, spec.num_agents)]
            for name, obj in prompt_files.items():
                row.append(prompt_from_json(obj, sc, h, has_tokenizer=tok is not None,
                                            where=f"{name} (scenario {idx[j]}): $",
                                            frame_period_s=spec.frame_period_s))
            singles += row
        prompts = stack_prompts(singles)
        k = len(names)
        prompts = jax.tree.map(lambda x: jnp.asarray(x.reshape((bs, k) + x.shape[1:])), prompts)
        out = rollout_model(model, view.replace(road=None), prompts, jax.random.fold_in(jax.random.key(seed), b),
                            options)
        out = jax.tree.map(np.asarray, out)
        host_prompts = jax.tree.map(np.asarray, prompts)
        map_inputs = []  # (tokens, gt lanes, gt valid) of every scenario j < real and prompt q, j-major
        for j in range(real):
            sc = jax.tree.map(lambda x: x[j], host_view)
            for q, name in enumerate(names):
                p = jax.tree.map(lambda x: x[j, q], host_prompts)
                o = jax.tree.map(lambda x: x[j, q], out)
                gxy = np.where(p.agent_given[..., None], p.xy, sc.xy) if p.agent_given is not None else sc.xy
                ghd = np.where(p.agent_given, p.heading, sc.heading) if p.agent_given is not None else sc.heading
                gv = np.where(p.agent_given, p.valid, sc.valid) if p.agent_given is not None else sc.valid
                gv = gv & ~p.removed()[None]
                row = {**{f"given_{k_}": v for k_, v in given_deviation(o, gxy, ghd, gv, p, h).items()},
                       **{f"agents_{k_}": v for k_, v in agent_figures(o, sc.xy, sc.valid, sc.size, p, h).items()},
                       **{f"cap_{k_}": v for k_, v in cap_violations(o, p, h).items()}}
                own = p.lanes is not None and bool(p.use_lanes)
                ln, lv = (p.lanes, p.lanes_valid) if own else (sc.polylines, sc.polyline_valid)
                # a hand-drawn road: the area its lanes cover; the log's own lanes given as a vector map
                # ("lanes": "log") are the store's road, whose drivable area is stored
                drawn = own and (name not in prompt_files or prompt_files[name].get("lanes") != "log")
                if drawn:
                    road, source = None, "given_lanes"
                else:
                    road, source = sc.road, "store" if sc.road is not None else "none"
                off = lane_offroad(o, p, h, ln, lv, road, size=sc.size, source=source)
                sources[name].add(off.pop("offroad_source"))
                row.update({f"lanes_{k_}": v for k_, v in off.items()})
                if tok is not None:  # scored below for the whole batch in one call
                    gt, gt_ok = vector_lanes_frames(np.asarray(ln), np.asarray(lv, bool), rollout_poses(o)[h:])
                    map_inputs.append((o.map_tokens[h:], gt, gt_ok))
                for k_, v in row.items():
                    acc[name].setdefault(k_, []).append(v)
                if render_dir and idx[j] < render_count:
                    pts = None
                    kw = {}
                    if tok is not None:
                        pts, logits = tok.decode_tokens(o.map_tokens)
                        kw = dict(lanes=np.asarray(pts), lanes_valid=np.asarray(logits) > 0)
                    if own:
                        kw.update(given_lanes=p.lanes, given_lanes_valid=p.lanes_valid)
                    rendered += list(render_rollout(
                        os.path.join(render_dir, f"{idx[j]:04d}_{name}"), pred_xy=o.xy, pred_heading=o.heading,
                        pred_valid=o.valid, log_xy=sc.xy, log_heading=sc.heading, log_valid=sc.valid, size=sc.size,
                        num_history=h, frame_period_s=spec.frame_period_s, title=f"#{idx[j]} {name}",
                        given=given_mask(p, h), size_px=size_px, **kw))
        if map_inputs:  # one decode and one compiled scoring call per batch: [K prompts, real scenarios, ...]
            stacked = [np.stack([x[i] for x in map_inputs]) for i in range(3)]
            stacked = [x.reshape((real, k) + x.shape[1:]).swapaxes(0, 1) for x in stacked]
            sums = decoded_map_sums(tok, *stacked, step_axis=0)
            for q, name in enumerate(names):
                maps[name] = add_sums(maps[name], {k_: v[q:q + 1] for k_, v in sums.items()})
        if b == 0:
            bar.set_description(f"rollout and scoring of {k} prompts", refresh=False)
        bar.update(real)
    bar.close()
    res = {}
    for name in names:
        a = acc[name]
        agg = lambda key, fn: _aggregate(a.get(key), fn)
        res[name] = {
            "given_max_xy_m": agg("given_max_xy_m", np.max),
            "given_max_heading_rad": agg("given_max_heading_rad", np.max),
            "given_validity_mismatch": agg("given_validity_mismatch", np.mean),
            "cap_violations": agg("cap_violations", np.sum),
            "cap": agg("cap_cap", np.max),
            "max_valid_slots": agg("cap_max_valid_slots", np.max),
            "offroad_share": agg("lanes_offroad_share", np.nanmean),
            "offroad_corner_share": agg("lanes_offroad_corner_share", np.nanmean),
            "offroad_source": "; ".join(OFFROAD_SOURCES[x] for x in sorted(sources[name])),
            "offroad_outside_geometry_share": agg("lanes_offroad_outside_geometry_share", np.nanmean),
            "offroad_share_lane_distance": agg("lanes_offroad_share_lane_distance", np.nanmean),
            "agent_ade_m": agg("agents_ade_m", np.nanmean),
            "agent_collision_share": agg("agents_collision_share", np.nanmean),
            "mean_lane_distance_m": agg("lanes_mean_lane_distance_m", np.nanmean),
            **reduce_map(maps[name]),
        }
    return {"scenarios": n, "split": split, "data": os.path.abspath(data), "prompts": res,
            "prompt_files": list(prompt_files), "render": rendered}
