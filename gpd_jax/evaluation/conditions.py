"""How well a rollout respects its prompt's conditions (`gpd_jax.prompts.Prompt`), beside the usual figures.

Per rolled-out scenario (host numpy, model-rate arrays):

* `given_deviation`: the largest distance (m) and heading difference (rad) between a given agent state and the
  rolled-out one, over every slot and frame the prompt takes from its given data (paths, the log until frame k,
  initial trajectories): 0 when the condition holds to float precision;
* `cap_violations`: slot-frames valid although hidden or beyond the agent cap (should be 0), and the largest
  number of valid agents in a generated frame;
* `lane_offroad`: the share of generated agent positions (future frames, slots the prompt does not give) farther
  than half a lane width from every given lane centreline (the distance to the polylines; the drivable-area
  queries of `gpd_jax.geometry` can replace it once they land);
* `agent_figures`: beside them, the usual ADE against the log and collision share of the generated agents;
* `lane_map_f1`: map F1 (the paper's, `gpd_jax.metrics.map`) of the lanes decoded from the rollout's map tokens
  of future frames against the given lanes seen from each frame's rolled-out ego (SLEDGE vector lanes,
  `gpd_jax.data.lanes.vector_lanes_frames`).
"""

from __future__ import annotations

import os
from typing import Any

import numpy as np

from gpd_jax.data.lanes import vector_lanes_frames
from gpd_jax.evaluation.maps import decode_map_tokens
from gpd_jax.metrics.map import map_metric_sums, reduce_map_metrics
from gpd_jax.prompts import Prompt

LANE_HALF_WIDTH_M = 1.75  # half of a 3.5 m lane: farther than this from every given centreline is off the road


def _np(p: Prompt) -> Prompt:
    import jax

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
    from gpd_jax.metrics.agents import box_overlap_pairwise

    gen = ~given_mask(prompt, num_history)
    gen[:num_history] = False
    v = np.asarray(out.valid)
    both = gen & v & np.asarray(log_valid)
    d = np.linalg.norm(np.asarray(out.xy) - np.asarray(log_xy), axis=-1)
    ov = np.asarray(box_overlap_pairwise(np.asarray(out.xy)[num_history:], np.asarray(out.heading)[num_history:],
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


def lane_offroad(out: Any, prompt: Prompt, num_history: int, lanes: np.ndarray, lanes_valid: np.ndarray,
                 half_width: float = LANE_HALF_WIDTH_M) -> dict[str, float]:
    """Share of generated agent positions (future frames, slots not given there) off the given lanes, and their
    mean distance to the nearest centreline."""
    gen = ~given_mask(prompt, num_history)
    gen[:num_history] = False
    sel = gen & np.asarray(out.valid)
    pts = np.asarray(out.xy)[sel]
    if not len(pts):
        return {"offroad_share": float("nan"), "mean_lane_distance_m": float("nan"), "positions": 0}
    d = distance_to_polylines(pts, np.asarray(lanes), np.asarray(lanes_valid, bool))
    return {"offroad_share": float((d > half_width).mean()), "mean_lane_distance_m": float(d.mean()),
            "positions": int(len(pts))}


def lane_map_sums(tokenizer, out_map_tokens: np.ndarray, ego_poses: np.ndarray, lanes: np.ndarray,
                  lanes_valid: np.ndarray) -> dict[str, np.ndarray]:
    """Map-metric sums (`gpd_jax.metrics.map.map_metric_sums`, frames pooled) of tokens i32[F, M] decoded with
    `tokenizer` against the given lanes (scene frame) seen from the poses f32[F, 3] the tokens were made around.
    Reduce with `reduce_map_metrics` (after adding the sums of several scenarios)."""
    pts, logits = decode_map_tokens(tokenizer, tokenizer.params, np.asarray(out_map_tokens))
    gt, gt_ok = vector_lanes_frames(np.asarray(lanes), np.asarray(lanes_valid, bool), np.asarray(ego_poses))
    sums = map_metric_sums(pts, logits, gt, gt_ok)
    return {k: np.asarray(v) for k, v in sums.items()}


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


def evaluate_prompts(model, data: str, split: str, prompt_files: dict[str, dict], *, num_scenarios: int | None,
                     batch_size: int = 8, seed: int = 0, render_count: int = 0, render_dir: str | None = None,
                     size_px: int = 320, log=print) -> dict[str, Any]:
    """Rolls out every scenario of a split under every prompt (JSON content by name) plus the unconditioned
    `traffic_simulation` for reference, in one compiled rollout per batch (per-scenario prompts [B, K]), and
    scores each prompt's conditions (module docstring). Returns {"prompts": {name: scores}, ...}."""
    import jax
    import jax.numpy as jnp

    from gpd_jax.data.loader import SplitSource, to_scene
    from gpd_jax.decoding import rollout_jit
    from gpd_jax.evaluation.maps import encode_map_frames
    from gpd_jax.evaluation.render import render_rollout
    from gpd_jax.prompts import prompt_from_json, prompt_from_task, stack_prompts
    from gpd_jax.spec import EvalError

    spec, tok = model.spec, model.tokenizer
    h = spec.num_history
    src = SplitSource(data, split, with_polylines=True)
    n = len(src) if num_scenarios is None else min(int(num_scenarios), len(src))
    if n == 0:
        raise EvalError(f"split {split!r} of {data} has no scenarios")
    names = ["reference_traffic_simulation"] + list(prompt_files)
    bs = max(1, min(batch_size, n))
    acc: dict[str, dict[str, list]] = {k: {} for k in names}
    maps: dict[str, Any] = {k: None for k in names}
    rendered = []
    for b in range(-(-n // bs)):
        idx = list(range(b * bs, min((b + 1) * bs, n)))
        real = len(idx)
        idx += [idx[-1]] * (bs - real)
        recs = [src[i] for i in idx]
        full = to_scene({k: np.stack([r[k] for r in recs]) for k in recs[0]})
        view = spec.view(full)
        if not np.asarray(view.map_valid).all():
            if tok is None:
                raise EvalError(f"{data}/{split} has no map tokens and the model has no map tokenizer")
            enc = np.asarray(encode_map_frames(tok, tok.params, full.polylines, full.polyline_valid, view.ego_pose))
            view = view.replace(map_tokens=np.where(np.asarray(view.map_valid)[..., None], view.map_tokens, enc
                                                    ).astype(np.int32), map_valid=np.ones_like(view.map_valid))
        singles = []
        for j in range(bs):
            sc = jax.tree.map(lambda x: np.asarray(x)[j], view)
            row = [prompt_from_task("traffic_simulation", spec.num_frames, spec.num_map_tokens, spec.num_agents)]
            for name, obj in prompt_files.items():
                row.append(prompt_from_json(obj, sc, h, has_tokenizer=tok is not None,
                                            where=f"{name} (scenario {idx[j]}): $",
                                            frame_period_s=spec.frame_period_s))
            singles += row
        prompts = stack_prompts(singles)
        k = len(names)
        prompts = jax.tree.map(lambda x: jnp.asarray(x.reshape((bs, k) + x.shape[1:])), prompts)
        extra = {} if prompts.lanes is None else dict(tok=tok, tok_params=tok.params)
        out = rollout_jit(model.graphdef, model.params, model.rest,
                          jax.tree.map(jnp.asarray, view.replace(polylines=None, polyline_valid=None)), prompts,
                          jax.random.fold_in(jax.random.key(seed), b), h, float(model.config.rollout.temperature),
                          **extra)
        out = jax.tree.map(np.asarray, out)
        for j in range(real):
            sc = jax.tree.map(lambda x: np.asarray(x)[j], view)
            for q, name in enumerate(names):
                p = jax.tree.map(lambda x: np.asarray(x)[j, q], prompts)
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
                row.update({f"lanes_{k_}": v for k_, v in lane_offroad(o, p, h, ln, lv).items()})
                if tok is not None:
                    maps[name] = add_sums(maps[name], lane_map_sums(tok, o.map_tokens[h:], rollout_poses(o)[h:],
                                                                    ln, lv))
                for k_, v in row.items():
                    acc[name].setdefault(k_, []).append(v)
                if render_dir and idx[j] < render_count:
                    pts = lv_ = None
                    kw = {}
                    if tok is not None:
                        pts, logits = decode_map_tokens(tok, tok.params, o.map_tokens)
                        kw = dict(lanes=np.asarray(pts), lanes_valid=np.asarray(logits) > 0)
                    if own:
                        kw.update(given_lanes=p.lanes, given_lanes_valid=p.lanes_valid)
                    rendered += list(render_rollout(
                        os.path.join(render_dir, f"{idx[j]:04d}_{name}"), pred_xy=o.xy, pred_heading=o.heading,
                        pred_valid=o.valid, log_xy=sc.xy, log_heading=sc.heading, log_valid=sc.valid, size=sc.size,
                        num_history=h, frame_period_s=spec.frame_period_s, title=f"#{idx[j]} {name}",
                        given=given_mask(p, h), size_px=size_px, **kw))
        log(f"batch {b + 1}: {real} scenarios x {k} prompts")
    res = {}
    for name in names:
        a = acc[name]
        agg = lambda key, fn: float(fn(np.asarray(a[key], np.float64))) if a.get(key) else float("nan")
        res[name] = {
            "given_max_xy_m": agg("given_max_xy_m", np.max),
            "given_max_heading_rad": agg("given_max_heading_rad", np.max),
            "given_validity_mismatch": agg("given_validity_mismatch", np.mean),
            "cap_violations": agg("cap_violations", np.sum),
            "cap": agg("cap_cap", np.max),
            "max_valid_slots": agg("cap_max_valid_slots", np.max),
            "offroad_share": agg("lanes_offroad_share", np.nanmean),
            "agent_ade_m": agg("agents_ade_m", np.nanmean),
            "agent_collision_share": agg("agents_collision_share", np.nanmean),
            "mean_lane_distance_m": agg("lanes_mean_lane_distance_m", np.nanmean),
            **reduce_map(maps[name]),
        }
    return {"scenarios": n, "split": split, "data": os.path.abspath(data), "prompts": res,
            "prompt_files": list(prompt_files), "render": rendered}
