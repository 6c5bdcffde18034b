"""Validation during stage-2 training: the loss over fixed batches and `traffic_simulation` rollouts of the first
validation scenes, scored (agent ADE / FDE at 3 / 5 / 8 s, agents valid at the current frame) against constant
velocity computed at the stored frame rate, as `gpd_jax.evaluate` scores it."""

from __future__ import annotations

import os

import jax

from gpd_jax.checkpoint import Model, model_spec
from gpd_jax.data import loader as data_loader
from gpd_jax.decoding import rollout_model
from gpd_jax.evaluation.scoring import baseline_predictions
from gpd_jax.metrics import agents as agent_metrics_lib
from gpd_jax.model import reads_lanes
from gpd_jax.spec import EvalError, spec_from_config
from gpd_jax.tasks import make_tasks
from gpd_jax.training.step import training_scene


class Validator:
    """Validation loss over fixed batches and traffic-simulation rollouts scored against constant velocity."""

    def __init__(self, config, data_dir: str, trainer):
        tc, m = config.train, config.model
        self.config, self.trainer = config, trainer
        view_spec = model_spec(config)
        split = config.data.val_split
        n_val = len(data_loader.SplitSource(data_dir, split))
        bs = int(tc.batch_size)
        n_batches = min(int(tc.eval_batches), n_val // bs)
        lanes = reads_lanes(m)  # its agents read the lane polylines
        self.loss_batches = []
        if n_batches:
            it = data_loader.make_loader(data_dir, split, bs, seed=12345, num_epochs=1, num_threads=2, prefetch=0,
                                         with_polylines=lanes)
            for _ in range(n_batches):
                self.loss_batches.append(view_spec.view(training_scene(next(it))))
            it.close()
        n_roll = min(int(tc.eval_rollout_scenarios), n_val)
        try:
            self.spec, _ = spec_from_config(config)
        except EvalError as e:
            print(f"validation rollouts off: {e}")
            n_roll = 0
        self.scenes = None
        if n_roll:
            self.scenes = training_scene(data_loader.load_split(data_dir, split, indices=range(n_roll),
                                                                with_polylines=lanes))
        if self.scenes is not None:
            # the model being trained, without parameters (each validation passes the current ones)
            self.model = Model(config=config, graphdef=trainer.graphdef, params=None, rest=trainer.rest,
                               spec=view_spec)
            self.view = self.model.prepare(self.scenes)
            # Constant velocity from the stored frame rate, as rollout.py scores it; fixed, so scored once here.
            cv_xy, cv_heading, _ = baseline_predictions(self.scenes, self.spec, with_lanes=False)["constant_velocity"]
            self.cv_scores = self._score(cv_xy, cv_heading)
            self.tasks = make_tasks(["traffic_simulation"], int(m.num_map_tokens), int(m.num_agents))

    def _score(self, xy, heading) -> dict[str, float]:
        v, spec = self.view, self.spec
        sums = agent_metrics_lib.agent_metric_sums(
            xy, heading, v.xy, v.valid, v.size, num_history=spec.num_history, eval_mask=v.valid[:, spec.current],
            horizons=spec.horizons, variant="corrected", dt=spec.frame_period_s)
        red = agent_metrics_lib.reduce_agent_metrics(sums)
        return {f"{k}_{hl}": val for hl, d in red.items() for k, val in d.items()
                if k in ("agent_ade", "agent_fde", "ego_ade", "agent_collision")}

    def __call__(self, params, step: int) -> dict[str, float]:
        out: dict[str, float] = {}
        if self.loss_batches:
            acc: dict[str, float] = {}
            for b in self.loss_batches:
                parts = jax.device_get(self.trainer.eval_step(params, b))
                for k, v in parts.items():
                    acc[k] = acc.get(k, 0.0) + float(v) / len(self.loss_batches)
            out.update(acc)
        if self.scenes is not None:
            pred = rollout_model(self.model, self.view, self.tasks, jax.random.key(step), params=params)
            pred = jax.tree.map(lambda x: x[:, 0], pred)  # the one task
            model, cv = self._score(pred.xy, pred.heading), self.cv_scores
            for k, v in model.items():
                out[f"rollout_{k}"] = v
                out[f"cv_{k}"] = cv[k]
                if k.startswith("agent_ade") and cv[k] > 0:
                    out[f"rollout_{k}_vs_cv"] = v / cv[k]
            ratios = [v for k, v in out.items() if k.endswith("_vs_cv")]
            if ratios:
                out["rollout_agent_ade_vs_cv_mean"] = sum(ratios) / len(ratios)
        return out


class Validators:
    """`Validator`s of one or several stores. One store: its record as is. Several: each store's keys prefixed
    by the store's name (`name/rollout_agent_ade_3s_vs_cv`), and unprefixed the means over the stores of the
    validation loss and of every agent ADE / constant-velocity ratio (`rollout_agent_ade_vs_cv_mean`: the mean
    of all stores' ratios at all horizons)."""

    def __init__(self, config, data_dirs, trainer):
        dirs = list(data_dirs)
        names = [os.path.basename(os.path.normpath(d)) for d in dirs]
        if len(set(names)) != len(names):
            names = dirs  # two stores of one name: their full paths
        self.parts = [(n, Validator(config, d, trainer)) for n, d in zip(names, dirs)]

    def __call__(self, params, step: int) -> dict[str, float]:
        if len(self.parts) == 1:
            return self.parts[0][1](params, step)
        out: dict[str, float] = {}
        losses, ratios = [], []
        for name, v in self.parts:
            rec = v(params, step)
            out.update({f"{name}/{k}": x for k, x in rec.items()})
            if "loss" in rec:
                losses.append(rec["loss"])
            ratios += [x for k, x in rec.items() if k.endswith("_vs_cv")]
        if losses:
            out["loss"] = sum(losses) / len(losses)
        if ratios:
            out["rollout_agent_ade_vs_cv_mean"] = sum(ratios) / len(ratios)
        return out
