"""Conditional generation with the shipped model on two constructed scenes (one compiled rollout):

1. a straight road, ego + three cars at 10 m/s; slot 3 (ahead) is given a braking path (3 m/s^2 to a stop):
   slot 3 must follow it exactly and the cars behind it should slow relative to the unconditioned rollout;
2. a hand-drawn single curved road with no map tokens at all: the lanes are encoded around every frame's ego
   inside the rollout; F1 of the decoded tokens against the drawn road, how far generated agents stray from
   it, and the same with the road given in the history only and the map generated afterwards.

    python examples/prompt_demo.py --out runs/prompt_demo     # prints the numbers, writes PNG/GIF + JSON
    python examples/prompt_demo.py --checkpoint gpd_maps --out OUT   # another model
"""

from __future__ import annotations

import argparse
import json
import os

import jax
import numpy as np

import gpd_jax
from gpd_jax.evaluation import conditions as cond
from gpd_jax.evaluation.render import render_rollout
from gpd_jax.fsutil import atomic_write_json
from gpd_jax.scene import TYPE_ID, Scene


def stored_scene(xy, heading, valid, polylines, poly_valid, num_slots=33, have_tokens=True):
    t = xy.shape[0]
    size = np.tile(np.array([[4.5, 1.9]], np.float32), (num_slots, 1))
    atype = np.full(num_slots, TYPE_ID["car"], np.int32)
    atype[0] = TYPE_ID["ego"]
    return Scene(xy=xy.astype(np.float32), heading=heading.astype(np.float32), valid=valid, size=size,
                 agent_type=atype, map_tokens=np.zeros((t, 64), np.int32), map_valid=np.full(t, have_tokens),
                 ego_pose=np.concatenate([xy[:, 0], heading[:, :1]], -1).astype(np.float32),
                 polylines=polylines, polyline_valid=poly_valid)


def straight_scene(num_stored=101, current=20, dt=0.1, slots=33):
    ts = (np.arange(num_stored) - current) * dt
    xy = np.zeros((num_stored, slots, 2)); valid = np.zeros((num_stored, slots), bool)
    for s, x0 in ((0, 0.0), (1, -15.0), (2, 13.0), (3, 26.0)):
        xy[:, s, 0] = x0 + 10.0 * ts
        valid[:, s] = True
    road = np.stack([np.linspace(-200, 300, 501), np.zeros(501)], -1)
    poly = np.zeros((1, 501, 2), np.float32); poly[0] = road
    # map tokens are encoded from the polyline by the model's tokenizer (Model.prepare)
    return stored_scene(xy, np.zeros((num_stored, slots)), valid, poly, np.ones((1, 501), bool), slots,
                        have_tokens=False)


def curved_road(radius=40.0):
    """A straight approach along +x, a 90-degree left bend of `radius`, then straight along +y (scene frame)."""
    a = np.stack([np.linspace(-80, 20, 101), np.zeros(101)], -1)
    th = np.linspace(0, np.pi / 2, 64)
    b = np.stack([20 + radius * np.sin(th), radius * (1 - np.cos(th))], -1)
    c = np.stack([np.full(81, 20 + radius), radius + np.linspace(0, 80, 81)], -1)
    return np.concatenate([a, b[1:], c[1:]], 0)


def along(road, s):
    """Points and headings at arc lengths s along a polyline."""
    seg = np.linalg.norm(np.diff(road, axis=0), axis=-1)
    cum = np.concatenate([[0], np.cumsum(seg)])
    x, y = np.interp(s, cum, road[:, 0]), np.interp(s, cum, road[:, 1])
    i = np.clip(np.searchsorted(cum, s) - 1, 0, len(seg) - 1)
    d = road[i + 1] - road[i]
    return np.stack([x, y], -1), np.arctan2(d[..., 1], d[..., 0])


def curved_scene(road, num_stored=101, current=20, dt=0.1, slots=33, v=8.0):
    ts = (np.arange(num_stored) - current) * dt
    s0 = 80.0  # the ego's arc length at the current frame: x = 0
    xy = np.zeros((num_stored, slots, 2)); hd = np.zeros((num_stored, slots)); valid = np.zeros((num_stored, slots), bool)
    for s, off in ((0, 0.0), (1, -14.0), (2, 14.0), (3, 30.0)):
        p, h = along(road, s0 + off + v * ts)
        xy[:, s], hd[:, s], valid[:, s] = p, h, True
    valid[current + 1:] = False  # only the history is known: the future is the model's
    # no map tokens and no polylines: the road exists only in the prompt
    return stored_scene(xy, hd, valid, None, None, slots, have_tokens=True)


def main(argv=None):
    ap = argparse.ArgumentParser()
    ap.add_argument("--out", default="runs/prompt_demo")
    ap.add_argument("--checkpoint", default=None, help="a shipped model's name or an exported GPD (default: the default model)")
    args = ap.parse_args(argv)
    model = gpd_jax.load_model(args.checkpoint)
    spec, tok = model.spec, model.tokenizer
    h, t_total = spec.num_history, spec.num_frames
    fut = np.arange(h, t_total)
    tau = (fut - (h - 1)) * spec.frame_period_s

    straight = straight_scene()
    xb = 26.0 + np.where(tau < 10 / 3, 10 * tau - 1.5 * tau ** 2, 100 / 6)
    brake = gpd_jax.make_prompt(model, straight, paths={3: {"frames": fut.tolist(),
                                                           "xy": np.stack([xb, 0 * xb], -1).tolist()}})
    plain = gpd_jax.make_prompt(model, straight)

    road = curved_road()
    curved = curved_scene(road)
    cview = curved
    road_given = gpd_jax.make_prompt(model, cview, lanes=[road.tolist()])
    road_history = gpd_jax.make_prompt(model, cview, base="scene_generation", lanes=[road.tolist()],
                                       map_frames=list(range(h)))
    # two scenes x two prompts each, one compiled rollout: Prompt [2, 2, ...]
    prompts = gpd_jax.stack_prompts([plain, brake, road_given, road_history])
    prompts = jax.tree.map(lambda x: x.reshape((2, 2) + x.shape[1:]), prompts)
    one = lambda sc: jax.tree.map(lambda x: x[0], model.prepare(jax.tree.map(
        lambda x: np.asarray(x)[None], sc)).replace(polylines=None, polyline_valid=None))
    # the straight scene's map tokens are encoded from its polyline by the tokenizer; the curved scene has none
    # (zeros, marked known): the prompt's lanes replace every frame's tokens
    view = jax.tree.map(lambda a, b: np.stack([np.asarray(a), np.asarray(b)]), one(straight), one(curved))
    fn = jax.jit(gpd_jax.make_rollout_fn(model))
    out = jax.tree.map(np.asarray, fn(model.params, jax.tree.map(jax.numpy.asarray, view),
                                      jax.tree.map(jax.numpy.asarray, prompts), jax.random.key(0)))
    res = {}
    o = lambda s, k: jax.tree.map(lambda x: x[s, k], out)
    p_plain, p_brake = o(0, 0), o(0, 1)
    res["braking"] = {
        "slot3_max_deviation_m": float(np.abs(p_brake.xy[h:, 3] - np.stack([xb, 0 * xb], -1)).max()),
        "final_x_plain": {s: float(p_plain.xy[-1, s, 0]) for s in range(4)},
        "final_x_brake": {s: float(p_brake.xy[-1, s, 0]) for s in range(4)},
        "travel_8s_plain_m": {s: float(p_plain.xy[-1, s, 0] - p_plain.xy[h - 1, s, 0]) for s in range(4)},
        "travel_8s_brake_m": {s: float(p_brake.xy[-1, s, 0] - p_brake.xy[h - 1, s, 0]) for s in range(4)},
    }
    ln, lv = np.asarray(road_given.lanes), np.asarray(road_given.lanes_valid)
    for k, name in ((0, "road_given"), (1, "road_history_only")):
        r = o(1, k)
        pr = jax.tree.map(lambda x: np.asarray(x)[1, k], prompts)
        sums = cond.lane_map_sums(tok, r.map_tokens[h:], cond.rollout_poses(r)[h:], ln, lv)
        hist = cond.lane_map_sums(tok, r.map_tokens[:h], cond.rollout_poses(r)[:h], ln, lv)
        res[name] = {"future_map": cond.reduce_map(sums), "history_map": cond.reduce_map(hist),
                     **cond.lane_offroad(r, pr, h, ln, lv),
                     "valid_agents_per_future_frame": r.valid[h:].sum(-1).tolist()}
        given = cond.given_mask(pr, h)
        pts, logits = tok.decode_tokens(r.map_tokens)
        os.makedirs(args.out, exist_ok=True)
        render_rollout(os.path.join(args.out, f"curved_{name}"), pred_xy=r.xy, pred_heading=r.heading,
                       pred_valid=r.valid, log_xy=np.asarray(view.xy[1]), log_heading=np.asarray(view.heading[1]),
                       log_valid=np.asarray(view.valid[1]), size=np.asarray(view.size[1]), num_history=h,
                       frame_period_s=spec.frame_period_s, title=f"curved road ({name})",
                       lanes=np.asarray(pts), lanes_valid=np.asarray(logits) > 0, given=given, given_lanes=ln,
                       given_lanes_valid=lv, view_m=50.0, size_px=360, panels=5)
    bp = p_brake
    render_rollout(os.path.join(args.out, "braking"), pred_xy=bp.xy, pred_heading=bp.heading, pred_valid=bp.valid,
                   log_xy=np.asarray(view.xy[0]), log_heading=np.asarray(view.heading[0]),
                   log_valid=np.asarray(view.valid[0]), size=np.asarray(view.size[0]), num_history=h,
                   frame_period_s=spec.frame_period_s, title="slot 3 brakes (given)",
                   given=cond.given_mask(jax.tree.map(lambda x: np.asarray(x)[0, 1], prompts), h), view_m=50.0,
                   size_px=360)
    print(json.dumps(res, indent=1))
    atomic_write_json(os.path.join(args.out, "demo.json"), res)
    return res


if __name__ == "__main__":
    main()
