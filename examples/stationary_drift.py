"""Do stopped agents stay stopped? Traffic simulation, then for every agent stationary at the current frame (below
0.5 m/s at the stored rate, the evaluation's motion split) how far it is from where it stood, generated against
logged, k model frames on.

In SUMO and in real logs most stopped vehicles stay where they are for seconds (parked, queued): the logged
median displacement is zero. A model whose median creeps forward pays for it at every horizon, and that creep is
what the stationary rows of the motion split charge it with (`python rollout.py`'s "motion_split").

    python examples/stationary_drift.py --checkpoint gpd_traffic --data data/mix_real_dev \
        --split val --scenarios 150 --json OUT.json

(The stationary-drift figures of docs/results.md come from this script.)
"""

from __future__ import annotations

import dataclasses
import json
import os
import sys

import jax
import numpy as np

import gpd_jax
from gpd_jax.fsutil import atomic_write_json

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from _store_cli import load_model_and_scenes, store_parser  # noqa: E402

QUANTILES = (0.5, 0.75, 0.9)


def stationary_drift(view: gpd_jax.Scene, xy_out, valid_out, num_history: int, frames=(1, 2, 3, 5, 8),
                     below_mps: float = 0.5) -> dict[str, dict]:
    """Displacement from the current frame of the agents (not the ego) stationary there.

    view: the model's frames and slots of the scenes with stored-rate velocities (`speed_view`:
    xy f32[B, T, A, 2], valid bool[B, T, A], velocity f32[B, T, A, 2]); xy_out f32[B, T, A, 2] /
    valid_out bool[B, T, A]: a rollout of them.
    For each k in `frames` (model frames after the current one, num_history - 1), over the agents stationary at
    the current frame and valid at frame c + k in both the log and the rollout: their count, the generated and
    logged displacement quantiles (`QUANTILES`, metres), the share of each beyond 1 m, and the mean error
    against the log next to a model that stays put (the mean logged displacement)."""
    c = num_history - 1
    xy, valid = np.asarray(view.xy), np.asarray(view.valid)
    speed = np.linalg.norm(np.asarray(view.velocity)[:, c], axis=-1)
    stopped = valid[:, c] & (speed < below_mps)
    stopped[:, 0] = False  # the ego is not an agent here
    xy_out, valid_out = np.asarray(xy_out), np.asarray(valid_out)
    res = {}
    for k in frames:
        if c + k >= xy.shape[1]:
            continue
        m = stopped & valid[:, c + k] & valid_out[:, c + k]
        gen = np.linalg.norm(xy_out[:, c + k] - xy[:, c], axis=-1)[m]
        log = np.linalg.norm(xy[:, c + k] - xy[:, c], axis=-1)[m]
        err = np.linalg.norm(xy_out[:, c + k] - xy[:, c + k], axis=-1)[m]
        q = lambda d: [float(v) for v in np.quantile(d, QUANTILES)] if d.size else None  # noqa: E731
        res[f"{k}"] = {"n": int(m.sum()), "generated_quantiles_m": q(gen), "logged_quantiles_m": q(log),
                       "generated_beyond_1m": float((gen > 1).mean()) if gen.size else None,
                       "logged_beyond_1m": float((log > 1).mean()) if log.size else None,
                       "error_m": float(err.mean()) if err.size else None,
                       "stay_put_error_m": float(log.mean()) if log.size else None}
    return res


def speed_view(model, scenes: gpd_jax.Scene) -> gpd_jax.Scene:
    """The model's frames and slots of stored-rate scenes, with stored-rate velocities whether or not the model
    reads them (the motion split's speed)."""
    return dataclasses.replace(model.spec, velocity_inputs=True).view(scenes)


def main(argv=None) -> int:
    args = store_parser(__doc__.split("\n\n")[0], "a data store").parse_args(argv)
    model, scenes, n = load_model_and_scenes(args)
    out = gpd_jax.rollout(model, scenes, "traffic_simulation", jax.random.key(0))
    res = {"checkpoint": args.checkpoint, "data": args.data, "split": args.split, "scenarios": n,
           "frame_period_s": model.spec.frame_period_s, "quantiles": list(QUANTILES),
           "frames": stationary_drift(speed_view(model, scenes), out.xy, out.valid, model.spec.num_history)}
    if args.json:
        atomic_write_json(args.json, res)
    print(json.dumps(res["frames"], indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
