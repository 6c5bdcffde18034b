"""Stage 1: training the map tokenizer (VQ-VAE + DETR lane decoder).

`train_and_evaluate(config, workdir)` is what `python train.py --config configs/map_tokenizer.py:VARIANT --workdir DIR`
runs. Per step: a batch of random (sample, frame) pairs is rasterized around the frame's ego pose inside the
jitted step, encoded, quantized, decoded to 50 lines, Hungarian-matched to the SLEDGE vector lanes of that
frame, and trained with 2 L1 + 5 BCE + VQ loss. AdamW with the codebook at its own learning rate, linear warm-up then cosine decay, global-norm
clipping. The codebook is initialised by k-means on encoder outputs
(at `train.kmeans_at_step`), and codes whose running usage falls below `restart_threshold / K` are re-seeded
from recent encoder outputs every `restart_every` steps. With `train.continuous_warmup` the decoder reads the
unquantized encoder outputs until that k-means (no VQ loss), the codes after it. With FSQ (`model.fsq_levels`) there
is no codebook: no k-means, no restarts, no VQ loss; with `train.continuous` no quantiser at all (the reference).
`train.init_from` starts from a trained tokenizer (its codebook kept, or its encoder and decoder under a fresh FSQ);
with `train.decoder_only` the encoder and codebook stay fixed, so the tokens do not change and
models trained on them stay valid, while the decoder trains on.

The workdir gets `config.json`, `metrics.jsonl` (one JSON object per log / evaluation) and orbax checkpoints in
`checkpoints/` (training resumes from the latest one).
"""

from __future__ import annotations

import os
import time
from typing import Any, Iterator, NamedTuple

import jax
import jax.numpy as jnp
import ml_collections
import numpy as np
import optax
import tqdm
from flax import nnx

from gpd_jax.config import config_differences
from gpd_jax.data.loader import parse_mixture
from gpd_jax.fsutil import atomic_write_text
from gpd_jax.map_tokenizer import core, load_tokenizer
from gpd_jax.map_tokenizer.data import frame_batches
from gpd_jax.map_tokenizer.evaluation import encoder_input, frame_arrays, make_eval_step, tokenizer_metrics
from gpd_jax.map_tokenizer.model import build_vqvae
from gpd_jax.map_tokenizer.raster import raster_channels
from gpd_jax.training.common import (MetricsLog, checkpoint_manager, compiled_once, restore_state, save_state,
                                     step_key)


class TrainState(NamedTuple):
    step: jax.Array  # i32[]
    params: Any
    opt_state: Any
    usage: jax.Array  # f32[K] EMA of each code's share of tokens
    kmeans_done: jax.Array  # bool[]


def build_model(config: ml_collections.ConfigDict, seed: int | None = None):
    """(graphdef, params) of a freshly initialised `MapVQVAE`; params is a pure dict of arrays."""
    model = build_vqvae(config, nnx.Rngs(config.seed if seed is None else seed))
    graphdef, state = nnx.split(model, nnx.Param)
    return graphdef, nnx.to_pure_dict(state)


# What `train.decoder_only` keeps fixed: everything that decides the tokens.
FROZEN_WHEN_DECODER_ONLY = ("encoder", "codebook", "fsq")


def make_optimizer(train_cfg: ml_collections.ConfigDict, params) -> optax.GradientTransformation:
    """Clip, then AdamW with the codebook at `codebook_lr` and the rest at `lr`, both warm-up + cosine."""

    def schedule(peak):
        return optax.warmup_cosine_decay_schedule(0.0, peak, max(1, train_cfg.warmup_steps),
                                                  max(train_cfg.num_steps, train_cfg.warmup_steps + 1),
                                                  peak * train_cfg.end_lr_factor)

    frozen = FROZEN_WHEN_DECODER_ONLY if train_cfg.decoder_only else ()
    labels = {k: jax.tree.map(lambda _: "frozen" if k in frozen else "codebook" if k == "codebook" else "net", v)
              for k, v in params.items()}
    return optax.chain(
        optax.clip_by_global_norm(train_cfg.grad_clip),
        optax.multi_transform({
            "net": optax.adamw(schedule(train_cfg.lr), weight_decay=train_cfg.weight_decay),
            "codebook": optax.adam(schedule(train_cfg.codebook_lr)),
            "frozen": optax.set_to_zero(),
        }, labels))


def loss_fn(graphdef, config, params, batch, quantized: bool | jax.Array = True):
    """(total loss, aux dict) for one batch; see the module docstring. `quantized` False: continuous latents."""
    inputs = encoder_input(config, batch)
    if config.train.decoder_only:  # no gradient work for the frozen encoder and codebook
        params = {k: jax.lax.stop_gradient(v) if k in FROZEN_WHEN_DECODER_ONLY else v for k, v in params.items()}
    out = core.forward(graphdef, params, inputs, quantized)
    lines, aux = core.line_loss(out["points"], out["logits"], batch["lanes"], batch["lanes_valid"], config.loss.w_l1,
                                config.loss.w_bce)
    total = lines + config.loss.vq_weight * out["vq_loss"]
    return total, dict(loss=total, l1=aux["l1"], bce=aux["bce"], vq=out["vq_loss"], idx=out["idx"], z=out["z"])


def make_train_step(graphdef, config, tx):
    num_codes = config.model.num_codes
    decay = config.train.usage_decay

    # With continuous warm-up the decoder reads the encoder's continuous outputs until k-means has run; with
    # train.continuous, always (no quantiser: the reference a quantiser's cost is measured against).
    warmup = bool(config.train.continuous_warmup)
    continuous = bool(config.train.continuous)

    def train_step(state: TrainState, batch):
        quantized = False if continuous else state.kmeans_done if warmup else True
        grad_fn = jax.value_and_grad(lambda p: loss_fn(graphdef, config, p, batch, quantized), has_aux=True)
        (_, aux), grads = grad_fn(state.params)
        updates, opt_state = tx.update(grads, state.opt_state, state.params)
        params = optax.apply_updates(state.params, updates)
        counts, used, ppl = core.code_stats(aux["idx"], num_codes)
        usage = decay * state.usage + (1 - decay) * counts / jnp.maximum(counts.sum(), 1.0)
        metrics = dict(loss=aux["loss"], l1=aux["l1"], bce=aux["bce"], vq=aux["vq"], batch_usage=used,
                       batch_perplexity=ppl, grad_norm=optax.tree.norm(grads))
        z = aux["z"].reshape(-1, aux["z"].shape[-1])
        return state._replace(step=state.step + 1, params=params, opt_state=opt_state, usage=usage), metrics, z

    return train_step


def compiled_steps(graphdef, config, tx):
    """(train step, eval step), jitted once per model structure and step-relevant config (`compiled_once`; the
    eval step depends on the structure and the raster settings alone)."""
    train = compiled_once(("map_tokenizer", graphdef, step_key(config)),
                          lambda: jax.jit(make_train_step(graphdef, config, tx), donate_argnums=(0,)))
    return train, compiled_once(("map_tokenizer_eval", graphdef, config.raster.to_json(), config.train.continuous),
                                lambda: jax.jit(make_eval_step(graphdef, config, diagnostics=False,
                                                               quantized=not config.train.continuous)))


def kmeans_init(graphdef, params, config, key, batches: Iterator[dict]):
    """Params with the codebook replaced by k-means centres of encoder outputs of `kmeans_rasters` rasters."""
    enc = jax.jit(lambda p, b: core.encode_latents(graphdef, p, encoder_input(config, b)))
    zs, n = [], 0
    while n < config.train.kmeans_rasters:
        b = next(batches)
        z = enc(params, frame_arrays(b))
        zs.append(z.reshape(-1, z.shape[-1]))
        n += z.shape[0]
    z = jnp.concatenate(zs)
    centres = jax.jit(core.kmeans, static_argnums=(2, 3))(key, z, config.model.num_codes, config.train.kmeans_iters)
    return core.with_codebook(params, centres)


def _to_tree(state: TrainState) -> dict:
    return dict(step=state.step, params=state.params, opt_state=state.opt_state, usage=state.usage,
                kmeans_done=state.kmeans_done)


def restore_or_init(config, workdir, graphdef, params, tx, mgr, kmeans_done: bool = False):
    num_codes = config.model.num_codes
    state = TrainState(jnp.zeros((), jnp.int32), params, tx.init(params),
                       jnp.full((num_codes,), 1.0 / num_codes, jnp.float32), jnp.asarray(kmeans_done))
    if mgr.latest_step() is None:
        return state, False
    # orbax hands back arrays committed to a device, a fresh state's are not; jit compiles per argument placement,
    # so a run resumed in the process that started it (`stop_after`, then again) compiled its train and eval steps
    # a second time. Uncommitted like a fresh state, the restored one reuses them.
    restored = jax.tree.map(lambda x: jnp.asarray(np.asarray(x)), restore_state(mgr, _to_tree(state)))
    return TrainState(**restored), True


def initial_params(config: ml_collections.ConfigDict, path: str, fresh=None):
    """Float32 params of the tokenizer at `path` (an export or a workdir) to start from (`train.init_from`);
    its model and raster settings must equal `config`'s.

    Exception: `config` may add direction channels (`raster.direction`) to a binary source. The stem kernel's
    weights for the occupancy channel are the source's and those for the new (cos, sin) channels start at zero,
    so the fine-tune starts from the source's tokens exactly and learns to read the lanes' heading.

    Another exception, for `train.decoder_only`: `config` may ask for a deeper decoder than the source's
    (`model.decoder.num_layers`). The source's layers are kept and each added layer starts as an exact identity
    (its attention output and second FFN projections are zero, the rest freshly initialised), so training
    starts from the source's reconstructions, with its tokens, and only gains capacity. `fresh`: freshly
    initialised params of `config`'s model to take the added layers from (built here when not given).
    """
    src = load_tokenizer(path)
    mine, theirs = raster_channels(config.raster), raster_channels(src.config.raster)
    raster_diff = config_differences(config.raster, src.config.raster, ignore=("direction",))
    if raster_diff or mine < theirs:
        raise ValueError(f"train.init_from {path}: its raster config differs in "
                         f"{raster_diff or 'direction (a directional source cannot start a binary tokenizer)'}")
    params = jax.tree.map(lambda x: jnp.asarray(x, jnp.float32), src.params)
    if mine > theirs:
        params = _with_direction_channels(params, mine)
    extra = _added_decoder_layers(config, src.config, path)
    swap = _quantiser_changes(config, src.config, path)
    if not (extra or swap):
        return params
    if fresh is None:
        _, fresh = build_model(config)
    if swap:  # the source's encoder and decoder, a fresh quantiser of config's kind
        params = {k: v for k, v in params.items() if k not in ("codebook", "fsq")}
        params.update({k: fresh[k] for k in ("codebook", "fsq") if k in fresh})
    if not extra:
        return params
    layers = dict(params["decoder"]["layers"])
    n_src = len(layers)
    for i in range(n_src, n_src + extra):
        layer = fresh["decoder"]["layers"][i]
        # Zero output projections: the residual branch adds nothing, so the layer is the identity at first.
        for branch in ("self_attn", "cross_attn"):
            layer[branch]["out"] = jax.tree.map(jnp.zeros_like, layer[branch]["out"])
        layer["ff2"] = jax.tree.map(jnp.zeros_like, layer["ff2"])
        layers[i] = layer
    return {**params, "decoder": {**params["decoder"], "layers": layers}}


def _with_direction_channels(params, channels: int):
    """Params of a binary tokenizer with the stem taking `channels`-channel rasters: space-to-depth puts input
    channel c of patch pixel k at (k * channels + c), so the source's weight of pixel k moves to channel 0 of it
    and the others are zero (the same function of a raster's occupancy channel)."""
    k = params["encoder"]["stem"]["conv"]["kernel"]  # [kh, kw, p*p, width]
    new = jnp.zeros(k.shape[:2] + (k.shape[2], channels) + k.shape[3:], k.dtype).at[:, :, :, 0].set(k)
    stem = {**params["encoder"]["stem"], "conv": {"kernel": new.reshape(k.shape[:2] + (-1,) + k.shape[3:])}}
    return {**params, "encoder": {**params["encoder"], "stem": stem}}


# The model fields a fine-tune may change when it swaps the quantiser (`_quantiser_changes`).
QUANTISER_FIELDS = ("fsq_levels", "num_codes")


def _quantiser_changes(config, src_config, path: str) -> bool:
    """True when `config` puts FSQ (`model.fsq_levels`) with other levels on the source tokenizer: the fine-tune
    keeps the source's encoder and decoder and starts FSQ's projections fresh. Raises for another change of the
    quantiser (a new VQ codebook would need its k-means; `train.decoder_only` keeps the source's tokens)."""
    diff = config_differences(config.model, src_config.model,
                              ignore=tuple(k for k in config.model.keys() if k not in QUANTISER_FIELDS))
    if not diff:
        return False
    if not config.model.fsq_levels or config.train.decoder_only:
        raise ValueError(f"train.init_from {path}: its model config differs in {diff}; a fine-tune may change the "
                         "quantiser only to FSQ (model.fsq_levels), and not with train.decoder_only")
    return True


def _added_decoder_layers(config, src_config, path: str) -> int:
    """How many decoder layers `config` adds to the source tokenizer's (0, or more with `train.decoder_only`);
    raises when the model configs differ in anything else (the quantiser aside: `_quantiser_changes`)."""
    mine, theirs = config.model, src_config.model
    diff = config_differences(mine, theirs, ignore=("decoder",) + QUANTISER_FIELDS)
    dec_diff = config_differences(mine.decoder, theirs.decoder, ignore=("num_layers",))
    extra = int(mine.decoder.num_layers) - int(theirs.decoder.num_layers)
    if diff or dec_diff:
        raise ValueError(f"train.init_from {path}: its model config differs in {diff or 'decoder: ' + dec_diff}")
    if extra < 0 or (extra and not config.train.decoder_only):
        raise ValueError(f"train.init_from {path}: its decoder has {theirs.decoder.num_layers} layers, the config "
                         f"{mine.decoder.num_layers}; only train.decoder_only may add layers (never remove them)")
    return extra


def train_and_evaluate(config: ml_collections.ConfigDict, workdir: str, stop_after: int | None = None
                       ) -> dict[str, float]:
    """Trains the map tokenizer described by `config` in `workdir` (resuming from its latest checkpoint; with
    `stop_after`, stopping with a checkpoint after that many steps of this call) and returns the last evaluation's
    metrics."""
    os.makedirs(workdir, exist_ok=True)
    atomic_write_text(os.path.join(workdir, "config.json"), config.to_json(indent=2))
    log = MetricsLog(workdir, tensorboard=False)
    tcfg = config.train
    key = jax.random.key(config.seed)

    graphdef, params = build_model(config)
    init_from = tcfg.init_from
    decoder_only = bool(tcfg.decoder_only)
    if decoder_only and not init_from:
        raise ValueError("train.decoder_only trains the decoder of an existing tokenizer: set train.init_from")
    if init_from:
        params = initial_params(config, init_from, fresh=params)
    tx = make_optimizer(tcfg, params)
    mgr = checkpoint_manager(workdir, tcfg.keep_checkpoints)
    # A started tokenizer keeps its codebook: no k-means; FSQ has no codebook to initialise, nor does a
    # continuous run use one.
    fsq = bool(config.model.fsq_levels)
    state, resumed = restore_or_init(config, workdir, graphdef, params, tx, mgr,
                                     kmeans_done=bool(init_from) or fsq or bool(tcfg.continuous))
    start = int(state.step)
    if resumed:
        print(f"resumed from step {start}")

    train_iter = frame_batches(config, config.data.train_split, tcfg.batch_size, seed=config.seed + start,
                               shuffle=True, repeat=True)

    # validation reads data.eval_dir, else the (first) training store
    eval_dir = config.data.eval_dir or parse_mixture(config.data.dir)[0][0]

    def eval_batches():
        return frame_batches(config, config.data.eval_split, tcfg.batch_size, seed=12345, shuffle=True,
                             repeat=False, max_batches=tcfg.eval_batches, data_dir=eval_dir)

    train_step, eval_step = compiled_steps(graphdef, config, tx)
    restart = jax.jit(core.restart_dead_codes, static_argnums=(4,))

    last_eval: dict[str, float] = {}
    window_t, window_n = time.perf_counter(), 0
    end = tcfg.num_steps if stop_after is None else min(tcfg.num_steps, start + int(stop_after))
    bar = tqdm.tqdm(range(start, end), initial=start, total=tcfg.num_steps, dynamic_ncols=True, mininterval=5.0)
    for step in bar:
        if not bool(state.kmeans_done) and step >= tcfg.kmeans_at_step:
            p = kmeans_init(graphdef, state.params, config, jax.random.fold_in(key, 1), train_iter)
            state = state._replace(params=p, kmeans_done=jnp.ones((), bool),
                                   usage=jnp.full_like(state.usage, 1.0 / config.model.num_codes))
            log.record(dict(step=step, event="kmeans_init"))
        batch = next(train_iter)
        state, metrics, z = train_step(state, frame_arrays(batch))
        window_n += tcfg.batch_size
        s1 = step + 1
        if (tcfg.restart_every and not decoder_only and not fsq and not tcfg.continuous
                and s1 % tcfg.restart_every == 0 and bool(state.kmeans_done)
                and s1 < tcfg.restart_until * tcfg.num_steps):
            cb, usage, n_dead = restart(jax.random.fold_in(key, 1000 + s1), core.codebook_of(state.params),
                                        state.usage, z, float(tcfg.restart_threshold))
            state = state._replace(params=core.with_codebook(state.params, cb), usage=usage)
            if int(n_dead):
                log.record(dict(step=s1, event="dead_code_restart", codes=int(n_dead)))
        if s1 % tcfg.log_every == 0 or s1 == tcfg.num_steps:
            m = {k: float(v) for k, v in jax.device_get(metrics).items()}
            dt = time.perf_counter() - window_t
            m["samples_per_s"] = window_n / max(dt, 1e-9)
            m["usage_ema_codes"] = float(jnp.sum(state.usage > 0.03 / config.model.num_codes))
            window_t, window_n = time.perf_counter(), 0
            bar.set_postfix(loss=f"{m['loss']:.3f}", l1=f"{m['l1']:.2f}", sps=f"{m['samples_per_s']:.1f}")
            log.record(dict(step=s1, split="train", **m))
        if s1 % tcfg.eval_every == 0 or s1 == tcfg.num_steps:
            last_eval = tokenizer_metrics(graphdef, state.params, config, eval_batches(), eval_step)
            log.record(dict(step=s1, split=config.data.eval_split, **last_eval))
            bar.write(f"step {s1} eval: " + ", ".join(f"{k}={v:.4g}" for k, v in last_eval.items()
                                                       if isinstance(v, (int, float))))
        if s1 % tcfg.checkpoint_every == 0 or s1 in (tcfg.num_steps, end):
            save_state(mgr, s1, _to_tree(state))
    mgr.wait_until_finished()
    return last_eval
