"""Functional experimentation: the rollout as a pure function of the parameters and the scene.

1. Sensitivity: shift every other agent's history sideways by d metres (a batch of d values under one
   `jax.vmap`) and see how far their 8 s positions move, against the unshifted rollout.
2. Gradient: the mean final-position error of a traffic-simulation rollout with respect to every parameter,
   through the differentiable (recompute) rollout, and the layers whose parameters move it most.

    python examples/functional.py [--data data/test] [--shifts -2,-1,1,2]
"""

import argparse
import os
import sys

import jax
import jax.numpy as jnp

import gpd_jax

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from _store_cli import example_scenes  # noqa: E402

p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
p.add_argument("--data", default=None, help="a data store (default: the README's data/test, else 4 simulated scenes)")
p.add_argument("--split", default="test")
p.add_argument("--shifts", default="-2,-1,-0.5,0.5,1,2", help="lateral history shifts in metres")
args = p.parse_args()

model = gpd_jax.load_model()
scenes = model.prepare(example_scenes(args.data, args.split, 1))  # the model's view, map tokens filled
tasks = gpd_jax.make_tasks(model, "traffic_simulation")
h = model.spec.num_history
key = jax.random.key(0)

# 1. Sensitivity to the history, many perturbations in one compiled call.
fn = gpd_jax.make_rollout_fn(model)


def shifted(d):
    dy = jnp.zeros_like(scenes.xy).at[:, :h, 1:, 1].set(d)  # agents 1.. moved sideways in the history only
    return fn(model.params, scenes.replace(xy=scenes.xy + dy), tasks, key).xy[0, 0, -1]  # final positions


shifts = jnp.asarray([float(s) for s in args.shifts.split(",")])
finals = jax.jit(jax.vmap(shifted))(jnp.concatenate([jnp.zeros(1), shifts]))  # [1 + shifts, A, 2], one compile
base, finals = finals[0], finals[1:]
valid = scenes.valid[0, h - 1, 1:]
moved = jnp.linalg.norm(finals[:, 1:] - base[1:], axis=-1)
for d, m in zip(shifts, moved):
    print(f"history shifted {float(d):+.1f} m -> agents' 8 s positions move {float(jnp.mean(m[valid])):.2f} m")

# 2. Gradient of a rollout metric with respect to the parameters (the recompute rollout is differentiable).
grad_fn = gpd_jax.make_rollout_fn(model, gpd_jax.RolloutOptions(method="recompute"))


def final_error(params):
    out = grad_fn(params, scenes, tasks, key)
    err = jnp.linalg.norm(out.xy[0, 0, -1] - scenes.xy[0, -1], axis=-1)
    ok = scenes.valid[0, -1] & scenes.valid[0, h - 1]
    return jnp.sum(jnp.where(ok, err, 0.0)) / jnp.maximum(jnp.sum(ok), 1)


loss, grads = jax.jit(jax.value_and_grad(final_error))(model.params)
norms = {"/".join(str(getattr(k, "key", getattr(k, "idx", k))) for k in path): float(jnp.linalg.norm(g))
         for path, g in jax.tree_util.tree_leaves_with_path(grads)}
print(f"mean 8 s error {float(loss):.2f} m; gradient norm {float(jnp.sqrt(sum(n * n for n in norms.values()))):.3g}")
for name, n in sorted(norms.items(), key=lambda kv: -kv[1])[:5]:
    print(f"  {n:9.3g}  {name}")
