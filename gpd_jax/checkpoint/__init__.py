"""GPD models on disk and in memory: build from a config, load (by name, an export or a training workdir), export.

    model = load_model()                                  # the default model (gpd_jax.zoo.DEFAULT_MODEL)
    model = load_model("gpd_planner")                     # a shipped model by name (gpd_jax.list_models())
    model = load_model("runs/gpd")                        # a train.py workdir: latest orbax step
    view = model.prepare(scenes)                          # stored-rate scenes -> what its rollout reads
    model.module                                          # the NNX `GPD` (nnx.merge of the parts below)
    model.graphdef, model.params, model.rest              # structure, trainable params, frozen state
    model.spec                                            # its view of a stored scene (gpd_jax.spec)
    model.tokenizer                                       # its map tokenizer (or None)

    soup = average_models(["runs/a/export", "runs/b/export"], [0.5, 0.5], config_from=1)  # weight-space average

An exported model is a directory with `config.json` (the full training config) and `params.npz` (the model's
`nnx.Param` leaves keyed by their path, float32 or float16). The map tokenizer whose frozen codebook embeds map
tokens is named by `config.model.map_tokenizer`: a folder of that name inside the model's own folder (what
`export_model(..., tokenizer_dir=...)` writes), else a shipped model of that name (`gpd_jax.zoo`), else a path
(absolute, relative to the model's folder, or relative to the working directory): `resolve_tokenizer_path`.
"""

from __future__ import annotations

import dataclasses
import os
import shutil
from typing import Any

import ml_collections
import numpy as np
from flax import nnx

from gpd_jax import zoo
from gpd_jax.config import config_from_json
from gpd_jax.fsutil import (atomic_directory, atomic_write_json, flatten_params, load_params_npz, restore_params,
                            unflatten_params)
from gpd_jax.map_tokenizer import MapTokenizer, load_tokenizer
from gpd_jax.model import GPD, PlanningHead
from gpd_jax.model.attention import KERNELS
from gpd_jax.model.transformer import resolve_decode_dtype
from gpd_jax.options import RolloutOptions
from gpd_jax.scene import Scene
from gpd_jax.spec import EvalError, ModelSpec, model_frame_period_s, spec_from_config

CONFIG_FILE = zoo.CONFIG_FILE
PARAMS_FILE = "params.npz"


@dataclasses.dataclass(frozen=True, eq=False)
class Model:
    """A GPD ready to roll out: the NNX structure and its state as pytrees, its config, spec and tokenizer.

    graphdef: the module structure (static; `nnx.split`). params: the trainable `nnx.Param` state (a pytree:
    what `gpd_jax.make_rollout_fn`'s function takes and what a gradient is taken with respect to). rest: the
    other state (the frozen map codebook). spec: the model's view of a stored scene. tokenizer: the map
    tokenizer named by its config (None if it has none). path: where it was loaded from (None if built).
    """

    config: ml_collections.ConfigDict
    graphdef: Any
    params: Any
    rest: Any
    spec: ModelSpec
    tokenizer: MapTokenizer | None = None
    path: str | None = None

    @property
    def module(self) -> GPD:
        """The NNX module (a fresh merge: changing it does not change this Model)."""
        return nnx.merge(self.graphdef, self.params, self.rest)

    def replace(self, **changes) -> "Model":
        return dataclasses.replace(self, **changes)

    def with_decode(self, dtype: str | None = None, attention: str | None = None) -> "Model":
        """This model with its rollout's KV cache / attention dtype (`model.decode_dtype`: "auto", "float32",
        "bfloat16") or attention path (`model.decode_attention`) changed: the same parameters, another compiled
        rollout (`gpd_jax.load_model().with_decode(dtype="float32")` keeps a GPU rollout in float32)."""
        cfg = self.config.copy_and_resolve_references()
        if dtype is not None:
            resolve_decode_dtype(dtype)  # a ValueError naming the allowed ones
            cfg.model.decode_dtype = dtype
        if attention is not None:
            if attention not in KERNELS:
                raise ValueError(f"decode attention {attention!r}: expected one of {KERNELS}")
            cfg.model.decode_attention = attention
        module = self.module
        module.decode_dtype, module.decode_attention = cfg.model.decode_dtype, cfg.model.decode_attention
        return self.from_module(module, cfg, self.tokenizer, self.path)

    def require_tokenizer(self, options: RolloutOptions | None = None, prompt_lanes: bool = False) -> None:
        """Raises EvalError when `options` (re-encoded log lanes, a warped map) or a prompt with its own lanes
        (`prompt_lanes`) need this model's map tokenizer and it has none: the one place that is checked."""
        if self.tokenizer is not None:
            return
        if prompt_lanes:
            what = "a vector-map prompt (lanes) needs the model's map tokenizer"
        elif options is not None and options.needs_tokenizer:
            what = ("log_map='lanes' re-encodes the log's lanes" if options.log_map == "lanes" else
                    "gen_map='warp' moves generated maps") + " with the model's map tokenizer"
        else:
            return
        raise EvalError(f"{what}, and the model has none (config.model.map_tokenizer is empty)")

    def prepare(self, scenes: Scene, options: RolloutOptions | None = None, reencode=None) -> Scene:
        """What this model's rollout reads, from stored-rate scenes [..., T_stored, A_stored, ...]
        (`gpd_jax.load_scenes`): its view (`spec.view`: its frames and slots, velocities for a velocity-input
        model) with every missing map token encoded by its map tokenizer from the scenes' lane polylines. The one
        preparation of scenes for a rollout: the API, evaluation, prompts, the simulator, training's validation and
        planning all go through it (the rollout itself drops lanes it does not read: `gpd_jax.decoding.rollout_model`).

        options: checked against the model (a tokenizer where they need one). reencode: bool[...] scenes whose
        stored map tokens another tokenizer made (encoded again). Raises EvalError naming what is missing."""
        self.require_tokenizer(options)
        view = self.spec.view(scenes)
        missing = ~np.asarray(view.map_valid).all(axis=-1)
        if reencode is not None:
            missing = missing | np.asarray(reencode, bool)
        if not missing.any():
            return view
        if self.tokenizer is None or view.polylines is None:
            raise EvalError("the scenes have no map tokens at the model's frames, and "
                            + ("the model has no map tokenizer" if self.tokenizer is None
                               else "no lane polylines to encode them from"))
        lead = np.shape(view.map_tokens)[:-2]
        flat = lambda x: np.reshape(np.asarray(x), (-1,) + np.shape(x)[len(lead):])
        enc = np.asarray(self.tokenizer.encode_frames(flat(view.polylines), flat(view.polyline_valid),
                                                      flat(view.ego_pose))).reshape(np.shape(view.map_tokens))
        tokens = np.where(missing[..., None, None], enc, np.asarray(view.map_tokens)).astype(np.int32)
        return view.replace(map_tokens=tokens, map_valid=np.ones_like(np.asarray(view.map_valid)))

    @classmethod
    def from_module(cls, module: GPD, config, tokenizer: MapTokenizer | None = None, path: str | None = None
                    ) -> "Model":
        graphdef, params, rest = nnx.split(module, nnx.Param, ...)
        return cls(config=config, graphdef=graphdef, params=params, rest=rest, spec=model_spec(config),
                   tokenizer=tokenizer, path=path)


def model_spec(config) -> ModelSpec:
    """The model's spec with the horizons of 3 / 5 / 8 s that fit its future (its whole future if none does)."""
    try:
        return spec_from_config(config)[0]
    except EvalError:
        t, h = int(config.model.num_frames), int(config.model.num_history)
        spec, _ = spec_from_config(config, (float(t - h) * model_frame_period_s(config),))
        return spec


def resolve_tokenizer_path(ref: str, checkpoint_dir: str | None = None) -> str:
    """The folder of the map tokenizer `ref` names ("" -> ""): a folder `ref` inside `checkpoint_dir`, a shipped
    model of that name (`gpd_jax.zoo.find`), an absolute path, or a path relative to `checkpoint_dir` or the working
    directory, in that order. Raises FileNotFoundError saying where it looked."""
    if not ref:
        return ref
    tried = []
    if checkpoint_dir and not os.path.isabs(ref):
        p = os.path.normpath(os.path.join(checkpoint_dir, ref))
        if os.path.isfile(os.path.join(p, CONFIG_FILE)):
            return p
        tried.append(p)
    named = zoo.find(ref)
    if named:
        return named
    p = os.path.abspath(ref)
    if os.path.isfile(os.path.join(p, CONFIG_FILE)):
        return p
    if p not in tried:
        tried.append(p)
    raise FileNotFoundError(f"map tokenizer {ref!r} not found: no tokenizer at {' or '.join(tried)}, and no model "
                            f"of that name in {zoo.where_searched()}")


def build_model(config, seed: int | None = None, codebook: np.ndarray | None = None,
                checkpoint_dir: str | None = None) -> GPD:
    """A freshly initialised GPD of a full config. Map tokens are embedded with `codebook` when given, else with
    the codebook of the map tokenizer `config.model.map_tokenizer` names (resolved relative to
    `checkpoint_dir` first), else a learned one. The frame period is `data.frame_stride * data.frame_period_s`.
    A config with a `plan_head` section also gets the planning head (`module.plan_head`, a
    `gpd_jax.model.PlanningHead`; `python train.py --config configs/gpd_planner.py` trains it)."""
    m = config.model
    if codebook is None and m.map_tokenizer:
        tok = load_tokenizer(resolve_tokenizer_path(m.map_tokenizer, checkpoint_dir))
        codebook = np.asarray(tok.codebook)
    seed = config.seed if seed is None else seed
    module = GPD(m, nnx.Rngs(seed), codebook=codebook, frame_period_s=model_frame_period_s(config))
    if "plan_head" in config:
        # The fine-tuned planner (gpd_jax.model.planning_head): its parameters live under "plan_head".
        module.plan_head = PlanningHead.from_config(config.plan_head, m, nnx.Rngs(seed + 1))
    return module


def is_exported(path: str) -> bool:
    return os.path.exists(os.path.join(path, PARAMS_FILE))


def tokenizer_reference(ref: str) -> str:
    """What a training run writes as `model.map_tokenizer`: a shipped model's name stays a name (it resolves
    wherever the run's exports go), a path becomes absolute (raises FileNotFoundError if it does not resolve)."""
    if not ref:
        return ref
    if zoo.find(ref):
        return ref
    return resolve_tokenizer_path(ref)


def export_model(params, config: ml_collections.ConfigDict, out_dir: str, dtype=np.float32,
                 tokenizer_dir: str | None = None) -> str:
    """Writes `config.json` + `params.npz` to `out_dir` atomically (a temporary directory renamed into place;
    other files already in `out_dir`, such as a README or evaluation files, are kept).

    With `tokenizer_dir`, the map tokenizer is copied into `out_dir` under its folder's name and the config names
    it, so the export loads wherever it is copied.
    """
    out_dir = os.path.abspath(out_dir)
    with atomic_directory(out_dir) as tmp:
        config = ml_collections.ConfigDict(config.to_dict())
        if tokenizer_dir:
            name = os.path.basename(os.path.normpath(tokenizer_dir))
            shutil.copytree(tokenizer_dir, os.path.join(tmp, name),
                            ignore=shutil.ignore_patterns("checkpoints", "*.jsonl", "eval", "README.md"))
            config.model.map_tokenizer = name
        flat = {k: v.astype(dtype) if np.issubdtype(v.dtype, np.floating) else v
                for k, v in flatten_params(params).items()}
        np.savez(os.path.join(tmp, PARAMS_FILE), **flat)
        with open(os.path.join(tmp, CONFIG_FILE), "w") as f:
            f.write(config.to_json(indent=2))
    return out_dir


def load_model(name_or_path: str | None = None, step: int | None = None) -> Model:
    """A GPD by name (`gpd_jax.list_models()`; None: the default, `gpd_jax.zoo.DEFAULT_MODEL`) or by path (an
    exported model directory, or a train.py workdir: its latest step, or `step`). Raises FileNotFoundError /
    ValueError naming the file."""
    path = zoo.resolve(name_or_path)
    cfg_path = os.path.join(path, CONFIG_FILE)
    config = config_from_json(cfg_path)
    if config.stage != "gpd":
        raise ValueError(f"{cfg_path}: stage is {config.stage!r}, not a GPD model")
    tok_path = resolve_tokenizer_path(config.model.map_tokenizer, path)
    tokenizer = load_tokenizer(tok_path) if tok_path else None
    codebook = None if tokenizer is None else np.asarray(tokenizer.codebook)
    graphdef, params, rest = nnx.split(build_model(config, codebook=codebook), nnx.Param, ...)
    if is_exported(path):
        params = load_params_npz(os.path.join(path, PARAMS_FILE), params)
    else:
        params = restore_params(path, params, step)
    return Model(config=config, graphdef=graphdef, params=params, rest=rest, spec=model_spec(config),
                 tokenizer=tokenizer, path=path)


SOUP_FILE = "soup.json"


def average_models(paths: list[str], weights: list[float] | None = None, config_from: int = 0,
                   mixed_tokenizers: bool = False) -> Model:
    """A weight-space average of GPDs ("model soup"; WiSE-FT's interpolation between a model and its fine-tune):
    params = sum_i weights[i] * params_i, computed in float64.

    The models must share one parameter structure (names and shapes) and one map codebook (the same tokenizer's
    tokens); averaging is meaningful between models fine-tuned from a common ancestor. The result takes the
    config (architecture options such as the lane residual, spec, tokenizer) of `paths[config_from]`.

    Args:
      paths: exported model directories or train.py workdirs (latest step), two or more.
      weights: one per model, >= 0, summing to 1 (within 1e-6); default equal weights.
      config_from: index of the model whose config the average uses.
      mixed_tokenizers: allow models whose map tokenizers differ; the average reads the tokens of
        `paths[config_from]`'s. Meaningful only when one model was fine-tuned onto those tokens from the others
        (a GPD moved to a re-fitted tokenizer, averaged back with its parent).
    Raises ValueError naming the offending model or parameter.
    """
    if len(paths) < 2:
        raise ValueError(f"averaging needs two or more models, got {len(paths)}")
    weights = [1.0 / len(paths)] * len(paths) if weights is None else [float(w) for w in weights]
    if len(weights) != len(paths):
        raise ValueError(f"{len(weights)} weights for {len(paths)} models")
    if any(not np.isfinite(w) or w < 0 for w in weights) or abs(sum(weights) - 1.0) > 1e-6:
        raise ValueError(f"weights must be >= 0 and sum to 1, got {weights}")
    if not 0 <= config_from < len(paths):
        raise ValueError(f"config_from {config_from} is not one of the {len(paths)} models")
    models = [load_model(p) for p in paths]
    base = models[config_from]
    flats = [flatten_params(m.params) for m in models]
    for m, flat in zip(models, flats):
        if set(flat) != set(flats[config_from]):
            diff = sorted(set(flat) ^ set(flats[config_from]))
            raise ValueError(f"{m.path}: parameters differ from {base.path}'s (e.g. {diff[:3]})")
        for k, v in flat.items():
            if v.shape != flats[config_from][k].shape:
                raise ValueError(f"{m.path}: parameter {k} has shape {v.shape}, {base.path} has "
                                 f"{flats[config_from][k].shape}")
        fp = None if m.tokenizer is None else m.tokenizer.fingerprint()
        base_fp = None if base.tokenizer is None else base.tokenizer.fingerprint()
        if fp != base_fp and not mixed_tokenizers:
            raise ValueError(f"{m.path}: map tokenizer {fp} differs from {base.path}'s {base_fp}: its tokens mean "
                             "other things (--mixed-tokenizers: average anyway, reading the tokens of the "
                             "--config-from model's tokenizer)")
    avg = {k: sum(w * f[k].astype(np.float64) for w, f in zip(weights, flats)).astype(v.dtype)
           for k, v in flats[config_from].items()}
    params = unflatten_params(base.params, avg, where="average")
    return dataclasses.replace(base, params=params, path=None)


def main(argv=None) -> int:
    """`python -m gpd_jax.checkpoint export WORKDIR OUT [--step N] [--tokenizer-ref PATH] [--float16]`;
    `python -m gpd_jax.checkpoint average MODEL MODEL [...] --out OUT [--weights W W ...] [--config-from I]
    [--tokenizer-ref PATH]` (a weight-space average, `average_models`; OUT/soup.json records the sources)."""
    from gpd_jax.cliargs import ArgumentParser, count0, output_dir, program, run_command

    p = ArgumentParser(prog=program("python -m gpd_jax.checkpoint"), description="export a trained GPD model")
    sub = p.add_subparsers(dest="cmd", required=True)
    e = sub.add_parser("export", help="a train.py workdir's checkpoint -> config.json + params.npz")
    e.add_argument("workdir")
    e.add_argument("out", type=output_dir)
    e.add_argument("--step", type=count0, default=None, help="default: the latest checkpoint")
    e.add_argument("--tokenizer-ref", default=None,
                   help="name the map tokenizer in the exported config (a shipped tokenizer's name, or a path "
                        "resolved next to the export first) instead of copying the tokenizer into it")
    e.add_argument("--float16", action="store_true", help="store parameters as float16 (half the size)")
    a = sub.add_parser("average", help="a weight-space average of models fine-tuned from a common ancestor")
    a.add_argument("models", nargs="+")
    a.add_argument("--out", type=output_dir, required=True)
    a.add_argument("--weights", type=float, nargs="+", default=None, help="one per model, summing to 1 (equal)")
    a.add_argument("--config-from", type=count0, default=0, help="index of the model whose config is used (0)")
    a.add_argument("--mixed-tokenizers", action="store_true",
                   help="allow models on different map tokenizers (a model fine-tuned onto new tokens averaged back "
                        "with its parent); the average reads the --config-from model's tokens")
    a.add_argument("--tokenizer-ref", default=None,
                   help="write this map-tokenizer path into the config instead of copying the tokenizer")
    def work():
        args = p.parse_args(argv)
        if args.cmd == "average":
            return _average_cli(args)
        model = load_model(args.workdir, args.step)
        dtype = np.float16 if args.float16 else np.float32
        out = _export_cli(model.params, model.config, args.out, args.tokenizer_ref, args.workdir, dtype)
        print(f"exported {args.workdir} -> {out}")

    return run_command("python -m gpd_jax.checkpoint", work, (FileNotFoundError, ValueError))


def _export_cli(params, config, out: str, tokenizer_ref: str | None, source: str, dtype=np.float32) -> str:
    """Exports for the command line: with `tokenizer_ref` the config names that tokenizer path (which must resolve
    from `out`), else the source's tokenizer is copied in."""
    if tokenizer_ref is not None:
        config.model.map_tokenizer = tokenizer_ref
        out = export_model(params, config, out, dtype=dtype)
        resolve_tokenizer_path(tokenizer_ref, out)  # fails loudly if the reference does not resolve
        return out
    tok = config.model.map_tokenizer or None
    return export_model(params, config, out, dtype=dtype,
                        tokenizer_dir=resolve_tokenizer_path(tok, source) if tok else None)


def _average_cli(args) -> int:
    import hashlib

    model = average_models(args.models, args.weights, args.config_from, args.mixed_tokenizers)
    config = model.config
    src = args.models[args.config_from]
    out = _export_cli(model.params, config, args.out, args.tokenizer_ref, src)
    weights = args.weights or [1.0 / len(args.models)] * len(args.models)

    def sha(path):
        f = os.path.join(path, PARAMS_FILE)
        return hashlib.sha256(open(f, "rb").read()).hexdigest() if os.path.isfile(f) else None

    atomic_write_json(os.path.join(out, SOUP_FILE), {
        "sources": [{"path": m, "weight": w, "params_sha256": sha(m)} for m, w in zip(args.models, weights)],
        "config_from": src, **({"mixed_tokenizers": True} if args.mixed_tokenizers else {})})
    print(f"averaged {len(args.models)} models -> {out}")
    return 0

