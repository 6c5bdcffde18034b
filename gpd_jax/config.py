"""Configs: every field of a GPD and of a map tokenizer, declared once here with its default.

A config is an `ml_collections.ConfigDict` with a `stage` ("gpd" or "map_tokenizer"). `gpd_config()` and
`map_tokenizer_config()` are the schemas: every field the library reads, with its default (the paper's GPD, the
official deployment size of the tokenizer). Nothing else in the package supplies a default for a config field.

* A config file (`configs/*.py`) defines `get_config()` (or `get_config(variant)`) returning one of these with the
  recipe's values set; `load_config("configs/FILE.py:VARIANT", ["--config.a.b=v", ...])` loads it and applies
  command-line overrides (the flax-examples convention). Values are parsed with the type of the existing field, and
  the config is locked: an unknown field or a value of the wrong type fails, naming the override.
* An exported model or a training workdir stores its full config as `config.json`; `config_from_json` reads it onto
  the schema, so a field it lacks takes its default and a field the schema does not know is an error naming the file.
"""

from __future__ import annotations

import ast
import importlib.util
import json
import os
from collections.abc import Sequence

import ml_collections

STAGES = ("gpd", "map_tokenizer")

# Fields of configs written by earlier versions, removed with the options they held (no shipped model uses them),
# and the value at which they did nothing: an old export holding that value loads; any other value is refused.
RETIRED_FIELDS = {
    "gpd": {"rollout.temperature": 0.0, "loss.moving_weight": 1.0, "model.agent_map_context": False,
            "model.map_extent_m": None, "model.agent_lane_context": False, "model.lane_context_steps": None,
            "model.lane_context_step_m": None, "model.lane_context_max_gap_m": None, "model.agent_modes": 0},
    "map_tokenizer": {"train.quantize": True, "train.init_decoder": True, "loss.every_layer": False},
}


def _section(**fields) -> ml_collections.ConfigDict:
    return ml_collections.ConfigDict(fields)


def gpd_config(plan_head: bool = False) -> ml_collections.ConfigDict:
    """Every field of a GPD config with its default: GPD-1 at the paper's size (the official code's values; T 101 =
    21 + 80 frames at 10 Hz, 33 agents, 64 map tokens, d 128, 6 layers, 8 heads, FFN 2048). `plan_head=True` adds
    the planning head's section and the training fields of its fine-tuning (`gpd_jax.model.PlanningHead`)."""
    c = ml_collections.ConfigDict()
    c.stage = "gpd"
    c.seed = 0
    c.model = _section(
        num_frames=101,            # T
        num_history=21,            # H: given frames, the current one included (2 s + current at 10 Hz)
        num_agents=33,             # A: ego (slot 0) + nearest vehicles
        num_map_tokens=64,         # M: an 8 x 8 grid
        codebook_size=128,         # K: map codes
        d_model=128,
        num_layers=6,
        num_heads=8,
        ffn_dim=2048,
        head_hidden=256,           # hidden width of the prediction heads
        xy_range=300.0,            # x, y representable in [-xy_range, xy_range) m
        xy_levels=(1.0, 0.01),     # metres per level of the agent tokenizer
        xy_code_dim=48,
        heading_levels_deg=(20.0, 1.0),
        heading_code_dim=32,
        attn_chunk_frames=8,       # key chunk (frames) of the chunked attention
        train_attention="flash",   # "flash": chunked, memory-linear; "dense": one masked softmax (short sequences)
        decode_attention="auto",   # rollout attention: "native" (fused CPU kernel), "xla", "xla_batched" or "auto"
                                   # (the fastest, measured on this machine: gpd_jax.model.autotune)
        decode_dtype="auto",       # rollout KV cache and attention: "float32", "bfloat16" (fp32 accumulation;
                                   # activations, norms and heads stay fp32) or "auto" (bfloat16 on GPUs, float32
                                   # on CPUs: the faster there, measured in docs/benchmarks.md)
        predict_delta=False,       # regress displacements from the input frame instead of absolute positions
        velocity_residual=False,   # with predict_delta: the residual over constant velocity
        velocity_inputs=False,     # not in the paper: tokens encode each agent's velocity; a head predicts the next
        velocity_range=50.0,       # vx, vy representable in [-velocity_range, velocity_range) m/s
        velocity_levels=(1.0, 0.05),
        velocity_code_dim=32,
        agent_lane_residual=False,  # not in the paper (needs velocity_residual): the base the heads add to is an
                                   # agent that keeps its lane (gpd_jax.geometry.lane_follow), where lanes are given
        agent_bins=0.0,            # not in the paper: w > 0 adds a sampling head, a categorical over w-metre cells
                                   # of each agent's next position's offset from the regressed one, which a rollout
                                   # samples at temperature > 0 (the regression heads stay: temperature 0 is the
        agent_bin_extent=(8.0, 3.0),  # paper's head); the cells span +- these metres along, across its heading
        lane_context_stride=4,     # lanes read every this-many stored points (1 m apart): 4 m segments
        map_tokenizer="",          # the map tokenizer whose frozen codebook embeds map tokens: a model name
                                   # (gpd_jax.list_models) or a path; "" learns a token table instead
    )
    c.data = _section(
        dir="",                    # a store with map tokens encoded, or a weighted mixture "DIR:0.7,DIR:0.3"
        val_dir="",                # where validation reads val_split ("": the first store of dir; "A,B": each)
        train_split="train",
        val_split="val",
        frame_stride=1,            # model frame k is stored frame k * frame_stride (stores are 10 Hz, 101 frames)
        frame_period_s=0.1,        # seconds between stored frames
    )
    c.loss = _section(
        position=5.0,
        heading=5.73,              # (180 / 3.14) * 0.1 as in the official code
        valid=1.0,
        map=1.0,
        velocity=2.0,              # velocity_inputs models only (m/s)
        agent_norm="smooth_l1",    # position / velocity loss: "smooth_l1" (official) or "euclidean" (the
                                   # pseudo-Huber of the error's length: gpd_jax.training.step)
        agent_norm_delta=0.05,     # the euclidean loss's pseudo-Huber width (m, m/s)
        modes=1.0,                 # agent_bins models: the sampling head's negative log-likelihood of the next state
    )
    c.train = _section(
        batch_size=16,
        steps=100_000,
        learning_rate=1e-3,
        warmup_steps=2_000,
        min_learning_rate=1e-6,
        weight_decay=1e-4,
        grad_clip=5.0,
        log_every=50,
        eval_every=1_000,          # validation loss + validation rollouts (0: never)
        eval_batches=8,            # validation loss over this many batches
        eval_rollout_scenarios=32,  # traffic-simulation rollouts scored against constant velocity
        best_metric="",            # a validation key, lower is better: the best validation's parameters are
                                   # exported to WORKDIR/best (and WORKDIR/best.json)
        eval_at_start=False,       # also validate before the first step
        checkpoint_every=500,
        keep_checkpoints=2,
        loader_threads=4,
        rollout_passes=0,          # > 0: future frames' agent inputs are the model's own predictions
        map_feedback=0.0,          # with rollout_passes: share of each batch whose future map tokens are its own too
        lane_context_drop=0.0,     # share of each batch's scenes whose future frames get no lanes (agent_lane_residual)
        closed_loop_top_k=0,       # > 0: closed-loop fine-tuning (CAT-K): future inputs are the model's own rollout
                                   # keeping the closest to the log of its top-K sampling cells (needs agent_bins)
        reward_samples=0,          # >= 2: reward fine-tuning over this many sampled rollouts per scene (GRPO-style)
        reward_temperature=0.5,    # the sampled rollouts' temperature
        reward_weights=(1.0, 1.0, 0.5),  # collision, offroad, progress weights of each agent's reward
        reward_scale=1.0,          # weight of the policy-gradient loss beside the supervised loss (the anchor)
        init_from="",              # an exported model or workdir whose parameters start this run (fine-tuning)
        trainable="all",           # "all", or "sampling_head": only the sampling head learns (the rest stays as
                                   # init_from left it, so temperature 0 rolls out exactly as that model)
    )
    if plan_head:
        c.plan_head = _section(
            num_future=8,          # poses planned (model frames)
            num_heads=4,
            ffn_dim=512,
            position_scale=10.0,   # metres per unit of the displacement output
            first_frame=-1,        # plans trained from this frame on (-1: the current frame) to T - 2
            position_weight=1.0,
            heading_weight=5.73 / 5.0,  # the GPD's heading : position loss ratio
            route_points=0,        # > 0: the head also reads where the route goes (the logged ego's path, as nuPlan
                                   # gives its planners the route): this many points along it ahead of the ego
            route_spacing_m=5.0,   # metres of route between them
            candidates="",         # "idm": the head chooses its plan among IDM's plans along the route at the
                                   # target speeds idm_speeds (PlanningHead; trained by the cross-entropy of the
                                   # one closest to the log); "": the paper's head, which draws its plan
            idm_speeds=(1.0, 3.0, 5.0, 7.0, 9.0, 11.0, 13.89),  # m/s (13.89: SUMO's default lane speed, the idm
                                   # planner's target)
            closed_loop_rounds=0,  # > 0 (cached features of a frozen backbone): DAgger rounds, evenly spread over
                                   # the steps: the head drives the simulator (log agents, the plan tracker) on
                                   # closed_loop_scenes training scenes, and the states it reaches, labelled with
                                   # the log's future, join the training scenes
            closed_loop_scenes=64,
        )
        c.train.backbone_lr_scale = 0.1  # the backbone's learning rate / the head's (0: frozen)
        c.train.gpd_loss_weight = 0.0    # > 0: also the GPD's teacher-forced loss (a second backbone pass)
        c.train.cache_features = False   # frozen backbone only: its outputs computed once per scene
    return c


def map_tokenizer_config() -> ml_collections.ConfigDict:
    """Every field of a map-tokenizer config with its default: the official deployment size (ResNet-50 encoder to
    8 x 8 cells, 128 x 128 codebook, DETR lane decoder d 512, 8 heads, 6 layers, FFN 2048, 50 lines x 20 points)."""
    c = ml_collections.ConfigDict()
    c.stage = "map_tokenizer"
    c.seed = 0
    c.data = _section(
        dir="",                    # stores (or netframes folders), or a weighted mixture "DIR:0.7,DIR:0.3"
        train_split="train",
        eval_split="val",
        eval_dir="",               # where validation reads eval_split ("": the first store of dir)
        num_workers=1,             # loader prefetch threads
        processes=0,               # training-stream loader processes (0: one thread); an accelerator needs several
        gt_recut="",               # the decoder's targets: "" the stored cut of the lanes into lines (the paper's),
                                   # or a gpd_jax.data.lanes.RECUT_MODES mode ("join_ends")
    )
    c.raster = _section(
        size=256,
        pixel_size=0.25,
        max_segment_length=1.0,    # lanes are resampled every 1 m: 4 samples per segment, gap-free
        direction=False,           # True: SLEDGE's 3 line channels (occupancy, cos, sin of the lane heading)
    )
    c.model = _section(
        grid=8,
        num_codes=128,
        commitment=0.25,
        fsq_levels=(),             # empty: a VQ codebook of num_codes learned codes; set (e.g. (8, 5, 5, 5)): finite
                                   # scalar quantisation with these levels, num_codes their product
        encoder=_section(
            kind="raster",         # "raster": the ResNet below over a lane raster (the paper's); "vector": the lane
                                   # polylines' segments read by model.vector (gpd_jax.map_tokenizer.vector)
            block="bottleneck",    # "basic" or "bottleneck" residual blocks
            stage_sizes=(3, 4, 6, 3),
            stage_strides=(1, 2, 2, 2),
            width=64,
            stem_patch=1,          # > 1: a lossless space-to-depth stem of this patch
            stem_kernel=7,
            stem_stride=2,
            stem_pool=True,
            norm_groups=32,
            head_channels=256,
            code_dim=128,
        ),
        vector=_section(           # the vector encoder (model.encoder.kind "vector"); unused by the raster one
            point_stride=2,        # points per segment (the stores keep a point every ~1 m)
            max_segments=512,      # segments kept per frame, nearest the ego first
            cell_margin=2.0,       # metres: a cell sees the segments whose midpoints lie this far outside it
            fourier=4,             # Fourier frequencies of a segment's midpoint
            d_model=128,
            num_heads=4,
            num_layers=2,
            ffn_dim=256,
        ),
        decoder=_section(
            d_model=512,
            num_heads=8,
            num_layers=6,
            ffn_dim=2048,
            num_queries=50,
            num_points=20,
            max_coord=32.0,        # points squashed to +-max_coord metres
        ),
    )
    c.loss = _section(w_l1=2.0, w_bce=5.0, vq_weight=1.0)
    c.train = _section(
        batch_size=64,
        num_steps=200_000,
        warmup_steps=5_000,
        lr=1e-4,                   # the official: 1e-4 for the network, 5e-3 for the quantizer, cosine to 1e-5
        codebook_lr=5e-3,
        end_lr_factor=0.1,
        weight_decay=0.0,
        grad_clip=1.0,
        kmeans_rasters=512,        # rasters whose encoder outputs initialise the codebook (64 cells each)
        kmeans_iters=20,
        kmeans_at_step=2_000,      # k-means once the encoder has warmed up (0: at initialisation)
        continuous_warmup=True,    # the decoder reads the continuous latents until k-means
        continuous=False,          # the decoder reads the continuous latents throughout (no quantiser, no k-means):
                                   # the reference a quantiser's cost is measured against, not a tokenizer
        init_from="",              # start from this tokenizer (an export or a workdir), keeping its codebook
        decoder_only=False,        # with init_from: train only the decoder (the tokens stay init_from's)
        usage_decay=0.99,
        restart_every=1_000,       # dead-code restart period in steps (0: never)
        restart_threshold=0.03,    # a code is dead below threshold / K of the recent tokens
        restart_until=0.8,         # share of training after which codes are no longer re-seeded
        log_every=50,
        eval_every=5_000,
        eval_batches=50,
        checkpoint_every=2_000,
        keep_checkpoints=2,
    )
    return c


def recipe_stages(stages: dict, name: str, where: str) -> list[tuple[str, str | None, dict]]:
    """The stages of a recipe that reach `name`, first to last: [(stage, the stage it starts from, its field
    changes)]. `stages`: {stage: (parent stage or None, {"section.field": value})}, as a config file with stages
    declares them (configs/gpd_traffic.py). Raises ValueError naming `where` for an unknown stage."""
    if name not in stages:
        raise ValueError(f"{where}: stage {name!r} is not one of {tuple(stages)}")
    chain = []
    while name is not None:
        chain.append((name, stages[name][0], stages[name][1]))
        name = stages[name][0]
    return chain[::-1]


def set_fields(cfg: ml_collections.ConfigDict, changes: dict) -> ml_collections.ConfigDict:
    """Sets {"section.field": value} (dotted paths of any depth) in `cfg`; returns it."""
    for key, value in changes.items():
        *parents, leaf = key.split(".")
        node = cfg
        for p in parents:
            node = node[p]
        node[leaf] = value
    return cfg


def schema(stage: str, plan_head: bool = False) -> ml_collections.ConfigDict:
    """The default config of a stage ("gpd", optionally with the planning head, or "map_tokenizer")."""
    if stage == "gpd":
        return gpd_config(plan_head)
    if stage == "map_tokenizer":
        return map_tokenizer_config()
    raise ValueError(f"stage {stage!r} is not one of {STAGES}")


def load_config(path: str | os.PathLike, overrides: Sequence[str] = ()) -> ml_collections.ConfigDict:
    """Loads `get_config()` from a python file and applies `--config.key=value` overrides. `FILE.py:ARG` calls
    `get_config(ARG)` (a config file with variants). The result is checked against the schema and locked."""
    path = os.fspath(path)
    arg = None
    if not os.path.isfile(path) and ":" in path:
        path, arg = path.rsplit(":", 1)
    if not os.path.isfile(path):
        raise FileNotFoundError(f"config file not found: {path}")
    spec = importlib.util.spec_from_file_location(f"_gpd_config_{abs(hash(path))}", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    if not hasattr(module, "get_config"):
        raise ValueError(f"config file {path} defines no get_config()")
    cfg = module.get_config() if arg is None else module.get_config(arg)
    check_schema(cfg, where=path if arg is None else f"{path}:{arg}")
    cfg.lock()
    apply_overrides(cfg, overrides, source=path)
    return cfg


def check_schema(cfg: ml_collections.ConfigDict, where: str) -> None:
    """Raises ValueError naming `where` and the field if `cfg` has a field its stage's schema lacks, lacks one it
    has, or holds a section where the schema has a value (or the reverse)."""
    stage = cfg.get("stage")
    if stage not in STAGES:
        raise ValueError(f"{where}: stage is {stage!r}; expected one of {STAGES}")
    ref = _flat(schema(stage, plan_head="plan_head" in cfg).to_dict())
    mine = _flat(cfg.to_dict())
    unknown, missing = sorted(set(mine) - set(ref)), sorted(set(ref) - set(mine))
    if unknown:
        raise ValueError(f"{where}: unknown config field {unknown[0]!r}" + (f" (and {len(unknown) - 1} more)"
                                                                         if len(unknown) > 1 else ""))
    if missing:
        raise ValueError(f"{where}: config field {missing[0]!r} is missing; build configs from "
                         "gpd_jax.config.gpd_config() / map_tokenizer_config()")


def _flat(d: dict, prefix: str = "") -> dict:
    out = {}
    for k, v in d.items():
        if isinstance(v, dict):
            out.update(_flat(v, f"{prefix}{k}."))
        else:
            out[f"{prefix}{k}"] = v
    return out


def apply_overrides(cfg: ml_collections.ConfigDict, overrides: Sequence[str], source: str = "config") -> None:
    """Applies overrides of the form `--config.a.b=v`, `config.a.b=v` or `a.b=v` in place."""
    for item in overrides:
        text = item[2:] if item.startswith("--") else item
        if text.startswith("config."):
            text = text[len("config."):]
        if "=" not in text:
            raise ValueError(f"override {item!r} is not of the form --config.key=value")
        key, raw = text.split("=", 1)
        parent = cfg
        parts = key.split(".")
        for p in parts[:-1]:
            if p not in parent or not isinstance(parent[p], ml_collections.ConfigDict):
                raise KeyError(f"override {item!r}: {source} has no field {key!r}")
            parent = parent[p]
        leaf = parts[-1]
        if leaf not in parent or isinstance(parent[leaf], ml_collections.ConfigDict):
            raise KeyError(f"override {item!r}: {source} has no field {key!r}")
        parent[leaf] = _parse_like(raw, parent[leaf], item)


def _parse_like(raw: str, old, item: str):
    if isinstance(old, bool):
        low = raw.lower()
        if low in ("1", "true", "yes"):
            return True
        if low in ("0", "false", "no"):
            return False
        raise ValueError(f"override {item!r}: expected a boolean")
    if isinstance(old, str) or old is None:
        if old is None:
            try:
                return ast.literal_eval(raw)
            except (ValueError, SyntaxError):
                return raw
        return raw
    try:
        value = ast.literal_eval(raw)
    except (ValueError, SyntaxError):
        raise ValueError(f"override {item!r}: cannot parse {raw!r} as {type(old).__name__}") from None
    if isinstance(old, float) and isinstance(value, int) and not isinstance(value, bool):
        value = float(value)
    if isinstance(old, tuple) and isinstance(value, list):
        value = tuple(value)
    if type(value) is not type(old) and not (isinstance(old, (list, tuple)) and isinstance(value, (list, tuple))):
        raise ValueError(f"override {item!r}: expected {type(old).__name__}, got {type(value).__name__}")
    return value


def split_config_args(argv: Sequence[str]) -> tuple[list[str], list[str]]:
    """Splits argv into (`--config.*` overrides, the rest) so argparse can parse the rest."""
    overrides = [a for a in argv if a.startswith("--config.")]
    rest = [a for a in argv if not a.startswith("--config.")]
    return overrides, rest


def config_differences(mine: ml_collections.ConfigDict, theirs: ml_collections.ConfigDict,
                       ignore: Sequence[str] = ()) -> str:
    """The top-level fields in which two config sections differ, as "k (theirs there, mine here), ..." ('' when
    they agree); fields in `ignore` are left out. Used to refuse starting a run from another model."""
    a, b = json.loads(mine.to_json()), json.loads(theirs.to_json())
    diff = sorted(k for k in set(a) | set(b) if k not in ignore and a.get(k) != b.get(k))
    return ", ".join(f"{k} ({b.get(k)!r} there, {a.get(k)!r} here)" for k in diff)


def config_from_json(path: str) -> ml_collections.ConfigDict:
    """A config written with `config.to_json()` (exports, workdirs), read onto its stage's schema: fields it lacks
    take their defaults, JSON lists come back as tuples. Raises ValueError naming the file when it cannot be read,
    has no known stage, or holds a field the schema does not know."""
    try:
        with open(path) as f:
            d = json.load(f)
    except (OSError, ValueError) as e:
        raise ValueError(f"{path}: unreadable config ({e})") from e
    if not isinstance(d, dict) or d.get("stage") not in STAGES:
        stage = d.get("stage") if isinstance(d, dict) else None
        raise ValueError(f"{path}: stage is {stage!r}; expected one of {STAGES}")
    cfg = schema(d["stage"], plan_head="plan_head" in d)
    flat, ref = _flat(d), _flat(cfg.to_dict())
    for key, neutral in RETIRED_FIELDS[d["stage"]].items():  # None: any value, the option being off
        if key in flat:
            value = flat.pop(key)
            if neutral is not None and value != neutral:
                raise ValueError(f"{path}: {key} = {value!r}: that option was removed from gpd_jax (no shipped "
                                 "model uses it); docs/model-lineage.md says which commit still has it")
    unknown = sorted(set(flat) - set(ref))
    if unknown:
        raise ValueError(f"{path}: unknown config field {unknown[0]!r} (written by another version of gpd_jax?)")
    for key, value in flat.items():
        *parents, leaf = key.split(".")
        node = cfg
        for p in parents:
            node = node[p]
        node[leaf] = _tuples(value)
    return cfg


def _tuples(x):
    if isinstance(x, list):
        return tuple(_tuples(v) for v in x)
    return x
