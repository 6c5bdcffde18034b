"""Stage-2 training: GPD on a data store with map tokens (`python train.py --config configs/gpd_tiny.py ...`).

* Data: `gpd_jax.data.loader.make_loader` (grain; seeded shuffle, a new permutation per epoch), every batch cut
  to the model's frames and agent slots with `Scene.subsample(config.data.frame_stride, ...)`. `data.dir` is one
  store or a weighted mixture of stores (`DIR:0.7,DIR:0.3`, `loader.parse_mixture`); validation reads
  `data.val_dir` (default: the first store; several stores separated by commas are each validated). Map tokens
  must have been encoded into every store (`python -m gpd_jax.map_tokenizer encode --data DIR`).
* Step: teacher forcing (`gpd_jax.training.step`): AdamW, linear warm-up then cosine decay, global-norm clipping;
  with `train.rollout_passes` > 0 the future frames' agent inputs are the model's own predictions.
  `train.init_from` (an exported model or a workdir) starts a new run from its parameters (fine-tuning).
* Parallelism: the batch is split over every device of every process (a 1-D `data` mesh, `jax.sharding`);
  parameters and optimizer state are replicated; XLA's partitioner inserts the gradient all-reduce. Several
  processes or hosts (`train.py --coordinator HOST:PORT --num-processes N --process-id I`, or `--distributed`;
  `gpd_jax.distributed`): each process loads only its block of every global batch (`loader.process_blocks`), so N
  processes train on the batches of one process, and a run resumes on any process count. On one CPU,
  `XLA_FLAGS=--xla_force_host_platform_device_count=N` exposes N devices.
* Checkpoints: orbax, every `train.checkpoint_every` steps, at the end, and when the run is stopped (Ctrl-C or
  SIGTERM). A restarted run restores the latest step and asks the loader for batches from that step on, so a
  stopped-and-resumed run is the same run (same data order, same step, same parameters).
* Logs: a tqdm bar (loss, samples/s), `WORKDIR/metrics.jsonl` (one JSON record per log/eval), TensorBoard event
  files when `tensorboardX` is installed. Every `train.eval_every` steps: validation loss over
  `train.eval_batches` fixed batches and `traffic_simulation` rollouts of the first
  `train.eval_rollout_scenarios` validation scenes, scored (agent ADE/FDE at 3/5/8 s, agents valid at the
  current frame) against constant velocity computed at the stored frame rate.
* `train.best_metric` (a key of the validation record, lower is better, e.g. `rollout_agent_ade_vs_cv_mean`):
  the parameters of the best validation so far are exported to `WORKDIR/best` (atomically) with
  `WORKDIR/best.json` ({"metric", "value", "step"}), and a resumed run keeps its best: the checkpoint a run
  chooses on its validation stores, when longer training starts to overfit. `train.eval_at_start` also
  validates before the first step (step 0: a fine-tune's starting point, which may stay the best).
* At the end the model is exported to `WORKDIR/export` (`gpd_jax.checkpoint.export_model`, with its map
  tokenizer), which `rollout.py --checkpoint` loads.
"""

from __future__ import annotations

import json
import os
import time
from typing import Any, Callable, Sequence

import jax
import ml_collections
import numpy as np
import tqdm
from flax import nnx
from jax.sharding import NamedSharding, PartitionSpec

from gpd_jax.checkpoint import (build_model, export_model, load_model, model_spec, resolve_tokenizer_path,
                                tokenizer_reference)
from gpd_jax.config import config_differences
from gpd_jax.data import loader as data_loader
from gpd_jax.data import store
from gpd_jax.data.errors import DataError
from gpd_jax.data.pack import check_packed
from gpd_jax.fsutil import atomic_write_text
from gpd_jax.map_tokenizer import load_tokenizer
from gpd_jax.model import MODE_HEAD, count_params, reads_lanes, samples_agents
from gpd_jax.parallel import data_mesh, replicate
from gpd_jax.scene import Scene
from gpd_jax.training.common import (MetricsLog, StopOnSigterm, checkpoint_manager, restore_state,
                                     save_state)
from gpd_jax.training.step import TrainState, make_trainer, training_scene, uses_road
from gpd_jax.training.validation import Validators


# ----------------------------------------------------------------------------------------------- data
def resolve_data_dir(path: str) -> str:
    """`config.data.dir` with every directory made absolute: one store, or a mixture `DIR:W,DIR:W`
    (`gpd_jax.data.loader.parse_mixture`; the weights as given)."""
    if not path:
        raise DataError("config.data.dir", "no data directory configured (set --config.data.dir=DIR)")
    mixture = data_loader.parse_mixture(path)
    if len(mixture) == 1:
        return os.path.abspath(mixture[0][0])
    return ",".join(f"{os.path.abspath(d)}:{w:.6g}" for d, w in mixture)


def store_dirs(data_dir: str) -> list[str]:
    """The stores of a (resolved) `config.data.dir`, one or a mixture's."""
    return [d for d, _ in data_loader.parse_mixture(data_dir)]


def validation_dirs(config: ml_collections.ConfigDict, data_dir: str) -> list[str]:
    """Where validation reads `data.val_split`: the stores of `data.val_dir` (one, or several separated by
    commas) if set, else the (first) training store."""
    val = str(config.data.val_dir)
    if not val:
        return [store_dirs(data_dir)[0]]
    return [resolve_data_dir(v.strip()) for v in val.split(",") if v.strip()]


def validation_dir(config: ml_collections.ConfigDict, data_dir: str) -> str:
    """The first of `validation_dirs` (the planning head validates on one store)."""
    return validation_dirs(config, data_dir)[0]


def _check_store(config, data_dir: str, split: str) -> int:
    check_packed(data_dir, int(config.data.frame_stride), int(config.model.num_agents))
    src = data_loader.SplitSource(data_dir, split)
    rec = src[0]
    t, a = rec["xy"].shape[:2]
    m = config.model
    need = int(config.data.frame_stride) * (int(m.num_frames) - 1) + 1
    if t < need or a < int(m.num_agents):
        raise DataError(os.path.join(data_dir, split), f"samples have {t} frames and {a} agent slots; the config "
                        f"needs {need} frames (stride {config.data.frame_stride}) and {m.num_agents} slots")
    stride = int(config.data.frame_stride)
    if not rec["map_valid"].any():
        raise DataError(os.path.join(data_dir, split), "no map tokens in this split; encode them first: "
                        f"python -m gpd_jax.map_tokenizer encode --data {data_dir} --frame-stride {stride}")
    if not rec["map_valid"][:need:stride].all():
        raise DataError(os.path.join(data_dir, split), f"map tokens are missing at some of the model's frames "
                        f"(every {stride}th); encode them: python -m gpd_jax.map_tokenizer encode --data "
                        f"{data_dir} --frame-stride {stride}")
    if rec["map_tokens"].shape[-1] != int(m.num_map_tokens):
        raise DataError(os.path.join(data_dir, split), f"{rec['map_tokens'].shape[-1]} map tokens per frame, "
                        f"config has {m.num_map_tokens}")
    return len(src)


def _check_token_source(data_dir: str, splits: Sequence[str], tokenizer_dir: str) -> None:
    """Refuses a store whose map tokens in any of `splits` (training and validation) were made by another
    tokenizer than the model's (its codebook would embed the wrong codes)."""
    fp = load_tokenizer(tokenizer_dir).fingerprint()
    for split in dict.fromkeys(splits):
        bad = store.foreign_map_token_shards(data_dir, split, fp)
        if bad:
            j = store.shard_indices(data_dir, split)[bad[0]]
            raise DataError(store.shard_dir(data_dir, split, j), f"the map tokens of {len(bad)} shard(s) of split "
                            f"{split!r}, this one first, were made by tokenizer "
                            f"{store.map_tokens_source(data_dir, split, j)}, not by the model's ({tokenizer_dir}, "
                            f"{fp}); re-encode them: python -m gpd_jax.map_tokenizer encode --checkpoint "
                            f"{tokenizer_dir} --data {data_dir}")


def check_token_sources(config: ml_collections.ConfigDict, data_dir: str) -> str:
    """`_check_token_source` for the training split of every store of `data_dir` (one or a mixture's) and, when
    the run validates, for the validation split where validation reads it (`validation_dir`). Sets
    `config.model.map_tokenizer` to what the run records (`tokenizer_reference`) and returns the tokenizer's
    folder ("" for a model without one)."""
    if not config.model.map_tokenizer:
        return ""
    config.model.map_tokenizer = tokenizer_reference(config.model.map_tokenizer)
    tok_dir = resolve_tokenizer_path(config.model.map_tokenizer)
    for d in store_dirs(data_dir):
        _check_token_source(d, (config.data.train_split,), tok_dir)
    if int(config.train.eval_every) > 0:
        for d in validation_dirs(config, data_dir):
            _check_token_source(d, (config.data.val_split,), tok_dir)
    return tok_dir


def initial_params(path: str, config, fresh=None):
    """Parameters of the model at `path` (exported or a workdir) to fine-tune from (`train.init_from`): its model
    config must equal `config.model`, except for the map tokenizer (a model moved onto re-fitted tokens of the
    same shape), `agent_lane_residual`, which adds no parameters (it moves the heads' base along the lanes) and
    may be on here and off there, and a sampling head (`agent_bins`) on here over a model without
    one, whose new head keeps its initial parameters from `fresh` (this run's initial parameters)."""
    src = load_model(path)
    ignore = ("map_tokenizer",)
    if config.model.agent_lane_residual and not src.config.model.agent_lane_residual:
        ignore += ("agent_lane_residual",)
    new_head = samples_agents(config.model) and not samples_agents(src.config.model)
    ignore += ("agent_bins", "agent_bin_extent") if new_head else ()
    diff = config_differences(config.model, src.config.model, ignore=ignore)
    if diff:
        raise ValueError(f"train.init_from {path}: its model config differs in {diff}")
    if new_head:
        if fresh is None:
            raise ValueError("initial_params: a model that adds a sampling head needs this run's initial parameters")
        return nnx.merge_state(src.params, nnx.split_state(fresh, MODE_HEAD, ...)[0])
    return src.params


# ----------------------------------------------------------------------------------------------- training
def _global_batch(local: Scene, mesh) -> Scene:
    sharding = NamedSharding(mesh, PartitionSpec("data"))
    return jax.tree.map(lambda x: jax.make_array_from_process_local_data(sharding, np.asarray(x)), local)


def train_and_evaluate(config: ml_collections.ConfigDict, workdir: str, stop_after: int | None = None,
                       quiet: bool = False) -> dict[str, Any]:
    """Trains the GPD of `config` in `workdir`, resuming from its latest checkpoint.

    Args:
      config: a full config (`gpd_jax.config.gpd_config()`, configs/*.py); `config.data.dir` names the data store.
      workdir: checkpoints, `config.json`, `metrics.jsonl`, `export/` go here.
      stop_after: stop (with a checkpoint) after this many steps of *this* invocation, as if interrupted; the
        schedule still follows `train.steps`, so a later call resumes the same run.
      quiet: no progress bar.

    Returns:
      {"step": last step, "train": last logged train metrics, "eval": last evaluation, "export": dir or None}.
    """
    tc = config.train
    data_dir, n_train, mesh, pindex = prepare_run(config)
    check_token_sources(config, data_dir)

    lead = pindex == 0
    os.makedirs(workdir, exist_ok=True)
    cfg_path = os.path.join(workdir, "config.json")
    if lead:
        if os.path.exists(cfg_path):
            with open(cfg_path) as f:
                old = json.load(f)
            if old.get("model") != json.loads(config.to_json()).get("model"):
                raise ValueError(f"{cfg_path}: the workdir holds a run with a different model config; "
                                 "use a new --workdir")
        atomic_write_text(cfg_path, config.to_json(indent=2))

    spec = model_spec(config)
    model = build_model(config)
    trainer, state = make_trainer(model, config)
    mgr = checkpoint_manager(workdir, int(tc.keep_checkpoints))
    if mgr.latest_step() is not None:
        state = TrainState(**restore_state(mgr, state._asdict()))
    elif tc.init_from:
        state = trainer.init_state(initial_params(str(tc.init_from), config, state.params))
    start = int(state.step)
    state = replicate(state, mesh)
    log = MetricsLog(workdir, enabled=lead)
    if start and lead:
        print(f"resumed {workdir} at step {start}")
    elif lead:
        print(f"training {count_params(model):,} parameters on {n_train} scenes, {mesh.devices.size} device(s)")

    validator = (Validators(config, validation_dirs(config, data_dir), trainer) if int(tc.eval_every) > 0
                 else None)

    def summary(ev: dict[str, float]) -> str:
        keys = [k for k in ev if k in ("loss", "position") or k.endswith(("_vs_cv", "_vs_cv_mean"))]
        return ", ".join(f"{k}={ev[k]:.4g}" for k in keys)

    return run_steps(config, trainer, state, data_dir=data_dir, workdir=workdir, mesh=mesh, spec=spec, mgr=mgr,
                     log=log, start=start, stop_after=stop_after, lead=lead, quiet=quiet, desc="gpd",
                     validate=validator,
                     postfix=lambda parts: {"sps": f"{parts['samples_per_s']:.1f}"}, summary=summary)


def prepare_run(config: ml_collections.ConfigDict) -> tuple[str, int, Any, int]:
    """What every training run checks first: the training store (resolved, with its number of training scenes),
    the device mesh, and a batch size that divides over its devices and processes. Returns (data_dir, n_train,
    mesh, process index)."""
    data_dir = resolve_data_dir(config.data.dir)
    n_train = sum(_check_store(config, d, config.data.train_split) for d in store_dirs(data_dir))
    if int(config.train.eval_every) > 0:
        for d in validation_dirs(config, data_dir):
            check_packed(d, int(config.data.frame_stride), int(config.model.num_agents))
    pcount = jax.process_count()
    mesh = data_mesh()
    bs = int(config.train.batch_size)
    if bs % mesh.devices.size or bs % pcount:
        raise ValueError(f"train.batch_size {bs} must be divisible by the {mesh.devices.size} devices and "
                         f"{pcount} processes")
    return data_dir, n_train, mesh, jax.process_index()


class BestTracker:
    """The best validation so far by `metric` (lower is better) of a run in `workdir`: `WORKDIR/best.json`
    ({"metric", "value", "step"}) beside the exported parameters in `WORKDIR/best`, read back on resume."""

    def __init__(self, workdir: str, metric: str, enabled: bool = True):
        self.metric, self.enabled = metric, bool(metric) and enabled
        self.path = os.path.join(workdir, "best.json")
        self.export_dir = os.path.join(workdir, "best")
        self.value, self.step, self._pending = None, None, None
        if self.enabled and os.path.exists(self.path):
            with open(self.path) as f:
                rec = json.load(f)
            if rec.get("metric") != metric:
                raise ValueError(f"{self.path}: the run chose its best by {rec.get('metric')!r}, this config by "
                                 f"{metric!r}; use a new --workdir")
            self.value, self.step = float(rec["value"]), int(rec["step"])

    def update(self, step: int, record: dict[str, float]) -> bool:
        """Whether the validation `record` of `step` is the best so far (then export, then `commit()`)."""
        if not self.enabled:
            return False
        if self.metric not in record:
            raise ValueError(f"train.best_metric {self.metric!r} is not in the validation record (keys: "
                             f"{', '.join(sorted(record))})")
        v = float(record[self.metric])
        if not np.isfinite(v) or (self.value is not None and v >= self.value):
            return False
        self._pending = (v, int(step))
        return True

    def commit(self) -> None:
        """Records the pending best after its parameters are exported (so best.json never names a missing export)."""
        self.value, self.step = self._pending
        atomic_write_text(self.path, json.dumps({"metric": self.metric, "value": self.value, "step": self.step}))


def run_steps(config: ml_collections.ConfigDict, trainer, state: TrainState, *, data_dir: str, workdir: str, mesh,
              spec, mgr, log: MetricsLog, start: int, stop_after: int | None, lead: bool, quiet: bool, desc: str,
              validate: Callable[[Any, int], dict[str, float]] | None, postfix: Callable[[dict], dict],
              summary: Callable[[dict], str],
              next_batch: Callable[[int], Any] | None = None) -> dict[str, Any]:
    """The training steps of a run (stage 2 and the planning head's), from `start` to `train.steps` (or
    `stop_after` more): batches from the seeded loader at the resumed step (or `next_batch(step, params)`, the
    batch of step `step` + 1, e.g. of cached features: a pure function of the step and the parameters reached
    there, so a resumed run sees the same batches), a jitted `trainer.train_step` on the device mesh, metrics every `log_every`, `validate(params,
    step)` every `eval_every`, checkpoints every `checkpoint_every` and on a stop (Ctrl-C, SIGTERM), the export
    when the run is complete.

    Returns {"step", "train": last logged train metrics, "eval": last evaluation, "export": dir or None}."""
    tc = config.train
    bs, pcount, pindex = int(tc.batch_size), jax.process_count(), jax.process_index()
    tok_dir = resolve_tokenizer_path(config.model.map_tokenizer) if config.model.map_tokenizer else ""
    lanes = reads_lanes(config.model)  # its agents read the lane polylines
    it = None if next_batch is not None else data_loader.make_loader(
        data_dir, config.data.train_split, bs // pcount, seed=int(config.seed), process_index=pindex,
        process_count=pcount, start_step=start, num_threads=int(tc.loader_threads),
        with_polylines=lanes or uses_road(config))
    total = int(tc.steps)
    end = total if stop_after is None else min(total, start + int(stop_after))
    last_train: dict[str, float] = {}
    last_eval: dict[str, float] = {}
    best = BestTracker(workdir, str(tc.best_metric), enabled=lead and validate is not None)
    bar = tqdm.tqdm(total=total, initial=start, dynamic_ncols=True, mininterval=2.0, disable=quiet or not lead,
                    desc=desc)

    def evaluate(step: int, params) -> dict[str, float]:
        ev = validate(params, step)
        log.write(step, config.data.val_split, ev)
        if lead:
            bar.write(f"step {step} val: " + summary(ev))
        if best.update(step, ev):
            export_model(jax.device_get(params), config, best.export_dir, tokenizer_dir=tok_dir or None)
            best.commit()
            bar.write(f"step {step}: best {best.metric} so far ({best.value:.4g}) -> {best.export_dir}")
        return ev

    if validate is not None and start == 0 and bool(tc.eval_at_start):
        last_eval = evaluate(0, state.params)  # a fine-tune's starting point: its best may be where it started
    step = start
    window_t, window_n = time.perf_counter(), 0
    with StopOnSigterm() as stop:
        try:
            while step < end and not stop.requested:
                if next_batch is not None:
                    view = next_batch(step, state.params)
                else:
                    view = spec.view(training_scene(next(it), uses_road(config)))
                    if not np.all(view.map_valid):
                        raise DataError(os.path.join(data_dir, config.data.train_split), f"a batch of step "
                                        f"{step + 1} has model frames without map tokens; encode every shard: "
                                        f"python -m gpd_jax.map_tokenizer encode --data {data_dir} --frame-stride "
                                        f"{config.data.frame_stride}")
                state, parts = trainer.train_step(state, _global_batch(view, mesh))
                step += 1
                window_n += bs
                bar.update(1)
                if step % int(tc.log_every) == 0 or step == end:
                    parts = {k: float(v) for k, v in jax.device_get(parts).items()}
                    parts["samples_per_s"] = window_n / max(time.perf_counter() - window_t, 1e-9)
                    window_t, window_n = time.perf_counter(), 0
                    last_train = parts
                    log.write(step, "train", parts)
                    bar.set_postfix(loss=f"{parts['loss']:.3f}", **postfix(parts))
                if validate is not None and (step % int(tc.eval_every) == 0 or step == total):
                    last_eval = evaluate(step, state.params)
                    window_t, window_n = time.perf_counter(), 0
                if step % int(tc.checkpoint_every) == 0 or step == total:
                    save_state(mgr, step, state._asdict())
        except KeyboardInterrupt:
            stop.requested = True
        finally:
            bar.close()
            if it is not None:
                it.close()
            if mgr.latest_step() != step:
                save_state(mgr, step, state._asdict(), force=True)
            mgr.wait_until_finished()
    exported = None
    if step == total and lead:
        exported = export_model(jax.device_get(state.params), config, os.path.join(workdir, "export"),
                                tokenizer_dir=tok_dir or None)
    return {"step": step, "train": last_train, "eval": last_eval, "export": exported}
