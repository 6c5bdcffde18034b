"""Benchmarks that print figures (never timed tests).

    python -m gpd_jax.bench realism [--data DIR --split test] [--rollouts 32] [--agents 32] [--scenarios 8]
        [--realism-config 2025] [--rules official corrected] [--repeats 3] [--json PATH] [--export-official NPZ]
        [--skip N] [--no-signals]

    seconds per scenario of the WOSAC-form realism metric (`gpd_jax.metrics.realism.scenario_realism`, compiled
    once, `vmap`ped over a batch of scenarios): K rollouts x 8 s at 10 Hz (11 history frames) x A agents. Scenes
    from a store (its road geometry) or, without `--data`, synthetic scenes on a synthetic city grid of roads;
    rollouts are the log's future with a random walk added (the metric's cost does not depend on the values).
    Each counting rule (`--rules`, default both) is compiled and timed on its own. `--export-official NPZ` writes
    the same scenes and rollouts for `tests/conformance/run_official.py`, to time the official code on them.

    python -m gpd_jax.bench rollout --config configs/gpd_paper.py --batch 1 16 --json PATH
        [--future-frames F] [--recompute-points K] [--repeats R] [--decode-attention auto native xla cudnn]
        [--decode-dtype float32 bfloat16] [--workload SCENARIOS] [--native-march native x86-64-v3]
        [--config.model.x=y ...]

    python -m gpd_jax.bench samples --data DIR [--split test] [--model gpd_sampling] [--samples 32] [--scenarios 4]
        [--tasks traffic_simulation] [--temperature 1] [--repeats 3] [--json PATH]

    K sampled futures of S scenes in one compiled rollout of a shipped model (`RolloutOptions(samples=K)`, the
    public path): seconds per scene and per sampled rollout, compile time, the KV cache bytes of the S x tasks x K
    rollouts and XLA's memory analysis of the compiled program (peak bytes, per scene), on a store's scenes.

    python -m gpd_jax.bench precision --data DIR [--split test] [--model NAME] [--json PATH]

    a shipped model's rollouts of a store's scenes under every task with a bfloat16 and a float32 KV cache: how far
    apart agents and map tokens end up (`precision_differences`).

`bench rollout` measures, in one run (so ratios are meaningful on a noisy shared machine):

* the peaks: `matmul_gflops` and `matmul_bf16_gflops` (a large fp32 / bf16 matmul, 4096^2 x 4096^2 by default) and
  `copy_gbps` (a device-to-device copy, read and write counted), the machine's ceilings;
* per run the roofline: useful FLOPs (`achieved_gflops`, below) and useful bytes (`bytes_per_scenario`: every frame
  step reads the visible keys and values of every layer and writes its own, and the weights once per batch;
  `achieved_gbps`) against both peaks (`achieved_over_matmul[_bf16]`, `achieved_over_copy`), the KV cache per
  scenario in its dtype, and the compiled program's memory (`memory`: XLA's analysis, on a CPU too: temporaries,
  arguments, outputs, peak and per scenario); `--workload N` also times N scenarios x 6 tasks in calls of the
  largest batch, compile excluded;
* cached rollout per scenario at each batch size (a batch that mixes all six tasks, random weights,
  synthetic scenes), with its compile time. A batch is sharded over the local devices (on a CPU, one XLA
  device per core; see gpd_jax/parallel.py), so batches use every core; batch 1 runs on one device. With
  `--decode-attention native xla` every batch size is measured with each attention kernel of the rollout
  (the fused native CPU kernel of gpd_jax/model/native.py, which uses every core by itself, and the pure-XLA one);
* `machine`: CPU model, instruction-set level (avx512/avx2/...), cores, JAX version and backend, so figures
  from different machines are never compared by accident; per run the native kernel's build target
  (`native_march`, `--native-march` to compare several in one run) and vector width, and for `auto` what it
  chose at each shape and why (`auto_choices`: timings of every candidate path, measured or read from the cache).
* the recompute rollout (the official method: a full forward over the whole prefix for every future frame,
  same model and weights) at batch 1, with the fastest full-prefix forward this machine has: dense attention
  (one masked softmax per layer, as the official code) and the chunked flash one are both timed at every prefix
  length and the faster counts (`recompute_forward` in the JSON says which won where). Timing 80 forwards of up to 9.7k tokens takes many minutes on a CPU,
  so by default a forward is timed at K prefix lengths spread over [H, T-1], a quadratic in the prefix
  length is fitted, and the fit is summed over every future frame's prefix; the JSON says so
  (`recompute_method`). `--recompute-points 0` runs the full recompute rollout instead.
* `achieved_gflops`: useful FLOPs of the cached rollout divided by its time. Useful FLOPs are counted
  analytically (`rollout_flops`): 2 per multiply-add of every linear layer on every token processed
  (embedding MLPs, q/k/v/out projections, FFN, heads) plus, for attention, 2 * d per (query, visible key)
  pair for scores and again for the value mix, where visible keys are the tokens of the query's own and
  earlier frames only (masked-out pairs and empty cache slots do not count).
"""

from __future__ import annotations

import functools
import json
import os
import statistics
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np
from flax import nnx

from gpd_jax import distributed, parallel
from gpd_jax.cliargs import ArgumentParser, UsageError, count, count0, nonnegative, output_file, program, run_command
from gpd_jax.model import autotune, native
from gpd_jax.model.attention import KERNELS
from gpd_jax.fsutil import atomic_write_json
from gpd_jax.config import load_config, split_config_args
from gpd_jax.model import GPD, forward
from gpd_jax.model.transformer import DECODE_DTYPES
from gpd_jax.decoding import rollout_batch, rollout_recompute
from gpd_jax.scene import TYPE_ID, wrap_angle
from gpd_jax.synthetic import synthetic_scenes
from gpd_jax.tasks import TASK_NAMES, make_tasks


def _log(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def _time(fn, repeats: int) -> float:
    """Median wall time of `fn()` (which must block until its result is ready)."""
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def matmul_gflops(n: int = 4096, repeats: int = 5, dtype=jnp.float32) -> float:
    """GFLOP/s of an n x n by n x n matmul of `dtype` under jit (accumulating in float32)."""
    ka, kb = jax.random.split(jax.random.key(0))
    a = jax.random.normal(ka, (n, n), jnp.float32).astype(dtype)
    b = jax.random.normal(kb, (n, n), jnp.float32).astype(dtype)
    f = jax.jit(lambda a, b: jnp.matmul(a, b, preferred_element_type=jnp.float32))
    f(a, b).block_until_ready()
    t = _time(lambda: f(a, b).block_until_ready(), repeats)
    return 2 * n**3 / t / 1e9


def copy_gbps(mib: int = 256, repeats: int = 5) -> float:
    """Memory bandwidth in GB/s of a device-to-device copy (read and write of `mib` MiB: an elementwise scale, which
    XLA cannot elide)."""
    x = jnp.ones((mib * 2**20 // 4,), jnp.float32)
    f = jax.jit(lambda x: x * 2.0)
    f(x).block_until_ready()
    t = _time(lambda: f(x).block_until_ready(), repeats)
    return 2 * x.nbytes / t / 1e9


def device_info() -> dict:
    """The machine (`native.machine_info`: CPU, cores, JAX, backend) and the accelerator: device kind and count."""
    dev = jax.devices()
    return dict(native.machine_info(), device=dev[0].device_kind, device_count=len(dev))


def linear_flops_per_token(m) -> tuple[float, float]:
    """(FLOPs per agent token, FLOPs per map token) of all linear layers, excluding attention itself."""
    d, ffn, hh = m.d_model, m.ffn_dim, m.head_hidden
    tok_dim = 2 * len(m.xy_levels) * m.xy_code_dim + len(m.heading_levels_deg) * m.heading_code_dim
    block = 2 * (d * 3 * d + d * d + 2 * d * ffn)
    trunk = m.num_layers * block
    agent = 2 * (tok_dim * d + d * d + d * d) + 3 * 2 * (d * hh + hh) + trunk
    mapt = 2 * d * d + 2 * (d * hh + hh * m.codebook_size) + trunk
    return float(agent), float(mapt)


def rollout_flops(m, num_frames: int, num_history: int) -> float:
    """Useful FLOPs of one cached rollout of one scenario (see the module docstring)."""
    n = m.num_map_tokens + m.num_agents
    fa, fm = linear_flops_per_token(m)
    per_frame_linear = m.num_agents * fa + m.num_map_tokens * fm
    frames_processed = num_frames - 1  # history in the prefill, then every future frame but the last
    linear = frames_processed * per_frame_linear
    # a query of frame f sees (f + 1) * n keys: 2 * d FLOPs for scores and 2 * d for the value mix each
    attn = sum(n * (f + 1) * n * 4 * m.d_model for f in range(frames_processed)) * m.num_layers
    return float(linear + attn)


def rollout_bytes(m, num_frames: int, cache_itemsize: int, param_bytes: int, batch: int) -> float:
    """Bytes a cached rollout of one scenario must move at the least (`rollout_flops`' frames): every frame step reads
    the keys and values of every visible token (its own and earlier frames) in every layer and writes its own
    frame's, and reads the weights once per batch (so 1/batch of them per scenario)."""
    n, d, layers = m.num_map_tokens + m.num_agents, m.d_model, m.num_layers
    steps = num_frames - 1
    reads = sum((f + 1) * n for f in range(steps)) * 2 * d * layers * cache_itemsize
    writes = steps * n * 2 * d * layers * cache_itemsize
    return float(reads + writes + steps * param_bytes / batch)


def memory_figures(compiled, batch: int) -> dict:
    """Peak memory of a compiled program from XLA's memory analysis (on a CPU too): temporaries, arguments and
    outputs (less what outputs alias), total and per scenario. A program sharded over devices is analysed per
    device: `batch` is then one device's share."""
    ma = compiled.memory_analysis()
    if ma is None:
        return {}
    peak = ma.temp_size_in_bytes + ma.argument_size_in_bytes + ma.output_size_in_bytes - ma.alias_size_in_bytes
    return {"temp_bytes": int(ma.temp_size_in_bytes), "argument_bytes": int(ma.argument_size_in_bytes),
            "output_bytes": int(ma.output_size_in_bytes), "peak_bytes": int(peak),
            "temp_bytes_per_scenario": ma.temp_size_in_bytes / batch, "peak_bytes_per_scenario": peak / batch}


def _mixed_tasks(batch: int, m):
    names = [TASK_NAMES[i % len(TASK_NAMES)] for i in range(batch)]
    return make_tasks(names, m.num_map_tokens, m.num_agents)


def bench_rollout(args, overrides) -> dict:
    cfg = load_config(args.config, overrides)
    m = cfg.model
    h = m.num_history
    future = args.future_frames if args.future_frames is not None else m.num_frames - h
    t_total = h + future
    if t_total > m.num_frames:
        raise UsageError(f"--future-frames {future}: history {h} + future exceeds num_frames {m.num_frames}")
    _log(f"devices: {jax.devices()}")
    machine = device_info()
    _log("machine: " + ", ".join(f"{k} {v}" for k, v in machine.items()))
    mm = matmul_gflops(args.matmul_size)
    mm16 = matmul_gflops(args.matmul_size, dtype=jnp.bfloat16)
    bw = copy_gbps(args.copy_mib)
    _log(f"peaks: matmul fp32 {mm:.1f} GFLOP/s, bf16 {mm16:.1f} GFLOP/s; copy {bw:.1f} GB/s")
    model = GPD(m, nnx.Rngs(cfg.seed))
    state = nnx.state(model)
    param_bytes = sum(x.nbytes for x in jax.tree.leaves(state))
    config_name = os.path.splitext(os.path.basename(args.config))[0]

    def cached(graphdef, state, scenes, tasks, keys):
        return rollout_batch(nnx.merge(graphdef, state), scenes, tasks, keys, h)  # greedy, the paper's

    runs = []
    flops = rollout_flops(m, t_total, h)
    kernels = args.decode_attention or [m.decode_attention]
    marches = args.native_march or [native.march()]
    dtypes = args.decode_dtype or [m.decode_dtype]
    # a native build per target: native runs (and auto) are measured with each
    variants = [(k, t, dt) for dt in dtypes for k in kernels
                for t in (marches if k in ("native", "auto") else [None])]
    for (kernel, target, dtype), batch in ((v, b) for v in variants for b in args.batch):
        if target is not None:
            os.environ["GPD_JAX_NATIVE_MARCH"] = target  # read while tracing
        model.decode_attention = kernel  # static attributes: part of the graph definition
        model.decode_dtype = dtype
        cache_dtype = model.cache_dtype()
        cache_bytes = 2 * m.num_layers * model.padded_len(t_total) * m.d_model * cache_dtype.itemsize
        graphdef = nnx.graphdef(model)
        scenes = synthetic_scenes(batch, batch, t_total, h, m.num_agents, m.num_map_tokens, m.codebook_size)
        tasks = _mixed_tasks(batch, m)
        keys = jax.random.split(jax.random.key(1), batch)
        ndev = parallel.devices_for_batch(batch, min(args.devices or len(jax.devices()), len(jax.devices())))
        mesh = parallel.data_mesh(ndev)
        scenes, tasks, keys = parallel.shard_batch((scenes, tasks, keys), mesh)
        state_b = parallel.replicate(state, mesh)
        cached_jit = jax.jit(parallel.data_parallel(functools.partial(cached, graphdef), mesh))
        logged = len(autotune._choice_log)
        t0 = time.perf_counter()
        compiled = cached_jit.lower(state_b, scenes, tasks, keys).compile()
        compile_s = time.perf_counter() - t0
        choices = autotune._choice_log[logged:]
        label = _label(kernel, choices)
        build = native.build_info() if "native" in label else None
        _log(f"batch {batch}, {label} attention, {cache_dtype.name} cache: compiled in {compile_s:.1f} s "
             f"({ndev} device(s))")
        for c in {json.dumps(_public(c), sort_keys=True): c for c in choices}.values():
            _log(f"  auto chose {c['choice']} ({c['source']}): {c['why']}")
        run = lambda: jax.block_until_ready(compiled(state_b, scenes, tasks, keys))
        run()
        t = _time(run, args.repeats)
        per = t / batch
        _log(f"batch {batch}: cached {per:.4f} s per scenario")
        moved = rollout_bytes(m, t_total, cache_dtype.itemsize, param_bytes, batch)
        workload = None
        if args.workload and batch == max(args.batch):
            workload = _workload(run, args.workload, batch, compile_s)
            _log(f"{args.workload} scenarios x {len(TASK_NAMES)} tasks: {workload['seconds']:.2f} s "
                 f"({workload['calls']} calls of batch {batch})")
        runs.append({
            "config": config_name, "batch": batch, "future_frames": future, "devices": ndev,
            "processes": jax.process_count(),
            "decode_attention": label, "decode_dtype": cache_dtype.name,
            "native_march": build["target"] if build else None,
            "native_vector_width": build["vector_width"] if build else None,
            "auto_choices": [_public(c) for c in {json.dumps(_public(c), sort_keys=True): c
                                                  for c in choices}.values()],
            "cached_s_per_scenario": per, "recompute_s_per_scenario": None, "speedup": None,
            "compile_s": compile_s, "achieved_gflops": flops * batch / t / 1e9,
            "kv_cache_bytes": cache_bytes * batch, "kv_cache_bytes_per_scenario": cache_bytes,
            "bytes_per_scenario": moved, "achieved_gbps": moved * batch / t / 1e9,
            "memory": memory_figures(compiled, batch // ndev), "workload": workload,
        })
    out = {"machine": machine, "matmul_gflops": mm, "matmul_bf16_gflops": mm16, "copy_gbps": bw,
           "rollout_gflop_per_scenario": flops / 1e9, "runs": runs}
    if 1 in args.batch:
        rec, method, rows = bench_recompute(model, m, cfg, t_total, h, args)
        for r in runs:
            if r["batch"] == 1:
                r["recompute_s_per_scenario"] = rec
                r["speedup"] = rec / r["cached_s_per_scenario"]
        out["recompute_method"] = method
        out["recompute_forward"] = rows
    for r in runs:
        r["achieved_over_matmul"] = r["achieved_gflops"] / mm
        r["achieved_over_matmul_bf16"] = r["achieved_gflops"] / mm16
        r["achieved_over_copy"] = r["achieved_gbps"] / bw
    return out


def _workload(run, scenarios: int, batch: int, compile_s: float) -> dict:
    """Wall seconds for `scenarios` scenarios under every task (`scenarios` x 6 rollouts) in calls of `batch`, one
    after another, compilation excluded (reported beside)."""
    rollouts = scenarios * len(TASK_NAMES)
    calls = -(-rollouts // batch)
    t0 = time.perf_counter()
    for _ in range(calls):
        run()
    return {"scenarios": scenarios, "tasks": len(TASK_NAMES), "rollouts": calls * batch, "calls": calls,
            "batch": batch, "seconds": time.perf_counter() - t0, "compile_s": compile_s}


def _public(choice: dict) -> dict:
    return {k: choice.get(k) for k in ("choice", "source", "why", "times_ms", "path")}


def _label(kernel: str, choices: list) -> str:
    """What ran: "xla", "xla_batched", "native[-march]" or "auto->native[...]" (auto's choices at this run's
    shapes)."""
    if kernel == "auto":
        picked = sorted({c["choice"] for c in choices}) or ["xla"]
        inner = "+".join(_label(p, []) for p in picked)
        return f"auto->{inner}"
    return f"native[{native.march()}]" if kernel == "native" else kernel


RECOMPUTE_ATTENTION = ("dense", "chunked")  # the full-prefix forward's attention: one masked softmax, or flash


def _with_attention(model, attention_kind: str):
    """`model`'s (graphdef, state) with its teacher-forced forward using `attention_kind` attention."""
    dense = model.dense_attention
    model.dense_attention = attention_kind == "dense"  # a static attribute: part of the graph definition
    try:
        return nnx.split(model)
    finally:
        model.dense_attention = dense


def bench_recompute(model, m, cfg, t_total: int, h: int, args) -> tuple[float, str, list[dict]]:
    """Seconds per scenario of the official full-prefix recompute rollout at batch 1, with the fastest
    attention this machine has for each prefix: dense (one masked softmax per layer, as the official code does)
    and chunked (flash) are both timed at every measured prefix length and the faster one counts.

    Returns (seconds, how it was measured, per prefix length {frames, dense_s, chunked_s, fastest}).
    """
    scene = synthetic_scenes(0, 1, t_total, h, m.num_agents, m.num_map_tokens, m.codebook_size)
    scene = jax.tree.map(lambda x: jnp.asarray(x[0]), scene)
    if args.recompute_points <= 0:
        task = jax.tree.map(lambda x: jnp.asarray(x[0]), _mixed_tasks(1, m))
        row = {"frames": f"{h}..{t_total - 1}"}
        for kind in RECOMPUTE_ATTENTION:
            graphdef, state = _with_attention(model, kind)
            f = jax.jit(lambda s, sc, tk, g=graphdef: rollout_recompute(nnx.merge(g, s), sc, tk, jax.random.key(0),
                                                                        h))
            jax.block_until_ready(f(state, scene, task))
            row[f"{kind}_s"] = _time(lambda: jax.block_until_ready(f(state, scene, task)), 1)
            _log(f"recompute ({kind} attention): whole rollout {row[f'{kind}_s']:.2f} s")
        row["fastest"] = min(RECOMPUTE_ATTENTION, key=lambda k: row[f"{k}_s"])
        return (row[f"{row['fastest']}_s"], "full recompute rollout timed end to end with dense and with chunked "
                f"attention (fixed-length buffer of all frames per step); the faster ({row['fastest']}) counts", [row])

    def prefix_forward(graphdef, s, xy, heading, valid, maps):
        mdl = nnx.merge(graphdef, s)
        p = xy.shape[0]
        hid = forward(mdl, mdl.embed(xy, heading, valid, maps, jnp.arange(p)))
        return mdl.predict(hid[-1:], xy[-1:], heading[-1:], valid[-1:], xy[-2:-1], valid[-2:-1])

    fwd = jax.jit(prefix_forward, static_argnums=0)
    splits = {kind: _with_attention(model, kind) for kind in RECOMPUTE_ATTENTION}
    lengths = np.unique(np.linspace(h, t_total - 1, args.recompute_points).round().astype(int))
    rows = []
    for p in lengths:
        row = {"frames": int(p)}
        for kind, (graphdef, state) in splits.items():
            a = (graphdef, state, scene.xy[:p], scene.heading[:p], scene.valid[:p], scene.map_tokens[:p])
            jax.block_until_ready(fwd(*a))
            row[f"{kind}_s"] = _time(lambda: jax.block_until_ready(fwd(*a)), max(1, args.repeats // 2))
        row["fastest"] = min(RECOMPUTE_ATTENTION, key=lambda k: row[f"{k}_s"])
        rows.append(row)
        _log(f"recompute: forward over {p} frames: " + ", ".join(f"{k} {row[f'{k}_s']:.3f} s"
                                                                  for k in RECOMPUTE_ATTENTION))
    times = [row[f"{row['fastest']}_s"] for row in rows]
    deg = min(2, len(lengths) - 1)
    coef = np.polyfit(lengths, times, deg)
    total = float(np.sum(np.polyval(coef, np.arange(h, t_total))))
    method = (f"forward over the prefix timed at {len(lengths)} prefix lengths {lengths.tolist()} frames with dense "
              f"and with chunked attention, the faster at each length "
              f"({[row['fastest'] for row in rows]}: s {[round(x, 4) for x in times]}), degree-{deg} fit summed "
              f"over the {t_total - h} prefixes [{h}, {t_total - 1}]")
    return total, method, rows


def _grid_road(blocks: int = 5, block_m: float = 40.0, street_m: float = 10.0):
    """A synthetic city grid: a square of road with `blocks` x `blocks` square blocks as holes (even-odd rule);
    every block outline and the outer square is a closed road edge."""
    from gpd_jax.geometry import RoadGeometry

    span = blocks * (block_m + street_m) + street_m
    lo = -span / 2
    rings = [np.array([[lo, lo], [-lo, lo], [-lo, -lo], [lo, -lo]])]
    for i in range(blocks):
        for j in range(blocks):
            x0, y0 = lo + street_m + i * (block_m + street_m), lo + street_m + j * (block_m + street_m)
            rings.append(np.array([[x0, y0], [x0 + block_m, y0], [x0 + block_m, y0 + block_m], [x0, y0 + block_m]]))
    polys = np.stack(rings).astype(np.float32)
    edges = np.concatenate([polys, polys[:, :1]], axis=1)
    n = len(rings)
    return RoadGeometry(polygons=polys, polygon_valid=np.ones((n, 4), bool), polygon_kind=np.zeros(n, np.int32),
                        edges=edges, edge_valid=np.ones((n, 5), bool), lanes=np.zeros((1, 2, 2), np.float32),
                        lane_valid=np.zeros((1, 2), bool))


def bench_realism(args) -> dict:
    from gpd_jax.metrics import realism

    h, f, k, a = 11, 80, args.rollouts, args.agents
    if args.data:
        from gpd_jax.data.loader import load_split

        scenes = load_split(args.data, args.split, indices=range(args.skip, args.skip + args.scenarios),
                            with_polylines=True)
        scenes = scenes[0] if isinstance(scenes, tuple) else scenes
        if scenes.road is None:
            raise ValueError(f"{args.data}: the store has no road geometry (rebuild it to get it)")
        if scenes.num_agents < a or scenes.num_frames < 21 + f:
            raise ValueError(f"{args.data}: {scenes.num_agents} agents x {scenes.num_frames} frames; the benchmark "
                             f"needs {a} x {21 + f}")
        scenes = scenes.subsample(1, h + f, a, start=21 - h)
        road = scenes.road
        source = f"{args.data}:{args.split}" + (f" from scene {args.skip}" if args.skip else "")
    else:
        scenes = synthetic_scenes(0, args.scenarios, h + f, h, a, 64, 512)
        road = jax.tree.map(lambda x: np.broadcast_to(x, (args.scenarios,) + x.shape), _grid_road())
        source = "synthetic scenes on a synthetic 5 x 5 city grid"
    budget = realism.edge_segment_budget(road)
    keys = jax.random.split(jax.random.key(0), args.scenarios)

    def rollouts(xy, key):
        steps = jax.random.normal(key, (k,) + xy.shape) * 0.05
        return xy[None] + jnp.cumsum(steps.at[:, :h].set(0.0), axis=1)

    # traffic lights where the store has signal states (format 2) and the 2025 configuration scores them
    signals = None if args.no_signals or args.realism_config != "2025" else getattr(scenes, "signals", None)
    lanes = None if signals is None or scenes.polylines is None else (scenes.polylines, scenes.polyline_valid)

    def one(xy, heading, valid, size, road, key, agent_type, sig, ln, rules):
        rep = lambda x: jnp.broadcast_to(x, (k,) + x.shape)  # noqa: E731
        return realism.scenario_realism(rollouts(xy, key), rep(heading), rep(valid), xy, heading, valid, size, h,
                                        road, config=args.realism_config, max_edge_segments=budget, rules=rules,
                                        agent_type=agent_type, signals=sig, lanes=None if ln is None else ln[0],
                                        lane_valid=None if ln is None else ln[1])

    inputs = (jnp.asarray(scenes.xy), jnp.asarray(scenes.heading), jnp.asarray(scenes.valid),
              jnp.asarray(scenes.size), jax.tree.map(jnp.asarray, road), keys, jnp.asarray(scenes.agent_type),
              jax.tree.map(jnp.asarray, signals), jax.tree.map(jnp.asarray, lanes))
    runs = {}
    for rules in args.rules:
        fn = jax.jit(jax.vmap(lambda *x, r=rules: one(*x, r)))
        t0 = time.perf_counter()
        compiled = fn.lower(*inputs).compile()
        compile_s = time.perf_counter() - t0
        out = jax.block_until_ready(compiled(*inputs))
        wall = _time(lambda: jax.block_until_ready(compiled(*inputs)), args.repeats)
        red = realism.reduce_realism(jax.device_get(out), args.realism_config, rules=rules)
        runs[rules] = {"compile_s": compile_s, "s_per_scenario": wall / args.scenarios,
                       "metametric": red["metametric"], "road_edge_inexact_share": red["road_edge_inexact_share"]}
    if args.export_official:  # what the official mode scores: agents that leave the log continued
        sim_xy, sim_h = jax.vmap(lambda xy, hd, v, key: realism.continue_missing(
            rollouts(xy, key), jnp.broadcast_to(hd, (k,) + hd.shape), jnp.broadcast_to(v, (k,) + v.shape), h))(
            inputs[0], inputs[1], inputs[2], keys)
        _export_official(args.export_official, scenes, sim_xy[:, :, h:], sim_h[:, :, h:], realism.edge_polylines,
                         road, h, None if signals is None else realism.official_signal_arrays(
                             signals, *(lanes or (None, None))))
    return {"machine": native.machine_info(), "source": source, "rollouts": k, "agents": a, "future_frames": f,
            "history_frames": h, "scenarios": args.scenarios, "edge_segment_slots": budget,
            "traffic_lights": signals is not None,
            "config": args.realism_config, "rules": runs}


def _export_official(path, scenes, sim_xy, sim_heading, edge_polylines, road, h, signals=None):
    """The benchmark's scenes and rollouts (future frames, every agent present) in the format
    `tests/conformance/run_official.py` reads (every agent valid at the current frame evaluated; the road edges
    as the metric orients them, `edge_polylines`; `signals`: `official_signal_arrays`, with the states and stop
    points added here)."""
    n = scenes.xy.shape[0]
    lines = [edge_polylines(jax.tree.map(lambda x, i=i: np.asarray(x[i]), road)) for i in range(n)]
    m, p = max(len(x) for x in lines), max(len(q) for x in lines for q in x)
    edges, edge_valid = np.zeros((n, m, p, 2), np.float32), np.zeros((n, m, p), bool)
    for i, x in enumerate(lines):
        for j, q in enumerate(x):
            edges[i, j, :len(q)], edge_valid[i, j, :len(q)] = q, True
    valid = np.asarray(scenes.valid)
    np.savez_compressed(path, names=np.array([f"bench_{i}" for i in range(n)]), log_xy=np.asarray(scenes.xy),
                        log_heading=np.asarray(scenes.heading), log_valid=valid, size=np.asarray(scenes.size),
                        is_vehicle=np.asarray(scenes.agent_type) != TYPE_ID["other"], evaluated=valid[:, h - 1],
                        sub_xy=np.asarray(sim_xy), sub_heading=np.asarray(sim_heading),
                        edges=edges, edge_valid=edge_valid,
                        **({} if signals is None else {**signals, "signal_state": np.asarray(scenes.signals.state),
                                                       "signal_stop": np.asarray(scenes.signals.stop)}))
    print(f"wrote {path}: {n} scenes for tests/conformance/run_official.py")


def bench_samples(args) -> dict:
    """`--samples` futures of `--scenarios` scenes under `--tasks` in one compiled rollout of a shipped model: time,
    compile time, KV cache bytes and XLA's memory analysis (the public path: `Model.prepare`, `rollout_jit` with
    `RolloutOptions(samples=K)`)."""
    import gpd_jax
    from gpd_jax.decoding import rollout_jit

    model = gpd_jax.load_model(args.model)
    spec, m = model.spec, model.config.model
    scenes = gpd_jax.load_scenes(args.data, args.split, indices=range(args.scenarios))
    source = f"{args.data}:{args.split}"
    opts = gpd_jax.RolloutOptions(temperature=args.temperature, samples=args.samples)
    view = jax.tree.map(jnp.asarray, model.prepare(scenes, opts))
    if not m.agent_lane_residual:
        view = view.replace(polylines=None, polyline_valid=None)
    tasks = jax.tree.map(jnp.asarray, gpd_jax.make_tasks(model, args.tasks))
    call = (model.graphdef, model.params, model.rest, view, tasks, jax.random.key(0), spec.num_history, opts)
    t0 = time.perf_counter()
    compiled = rollout_jit.lower(*call).compile()
    compile_s = time.perf_counter() - t0
    run = lambda: jax.block_until_ready(compiled(*call[1:6]))  # noqa: E731
    out = run()
    wall = _time(run, args.repeats)
    s, k = view.xy.shape[0], len(args.tasks)
    rollouts = s * k * args.samples
    gm = model.module
    cache = 2 * m.num_layers * gm.padded_len(spec.num_frames) * m.d_model * gm.cache_dtype().itemsize
    gen = np.asarray(out.xy)[:, :, :, spec.num_history:]
    return {"machine": device_info(), "model": args.model or "default", "source": source, "scenarios": s,
            "tasks": list(args.tasks), "samples": args.samples, "temperature": args.temperature,
            "rollouts": rollouts, "compile_s": compile_s, "s_per_scenario": wall / s, "s_per_rollout": wall / rollouts,
            "kv_cache_bytes_per_rollout": cache, "kv_cache_bytes_per_scenario": cache * k * args.samples,
            "kv_cache_bytes": cache * rollouts, "memory": memory_figures(compiled, s),
            "sample_spread_m": float(np.nanmean(np.std(gen, axis=2)))}


def precision_differences(a, b, num_history: int, frame_period_s: float) -> dict:
    """How far rollouts `b` are from rollouts `a` of the same scenes and tasks (RolloutOutput [B, K, T, ...] as
    numpy), over the generated frames t >= num_history: agent position |xy_a - xy_b| (m) and heading difference
    (rad, wrapped) over slots valid in both, per horizon (seconds after the last history frame) and over all
    generated frames (mean, 99th percentile, max); the share of slots whose validity agrees and of map tokens
    that agree."""
    h = num_history
    both = np.asarray(a.valid)[:, :, h:] & np.asarray(b.valid)[:, :, h:]
    dxy = np.linalg.norm(np.asarray(a.xy)[:, :, h:] - np.asarray(b.xy)[:, :, h:], axis=-1)
    dh = np.abs(np.asarray(wrap_angle(np.asarray(a.heading)[:, :, h:] - np.asarray(b.heading)[:, :, h:])))

    def stats(x, m):
        x = x[m]
        return ({"mean": float(x.mean()), "p99": float(np.percentile(x, 99)), "max": float(x.max())} if x.size
                else {"mean": None, "p99": None, "max": None})

    per_horizon = {}
    for i in range(dxy.shape[2]):
        per_horizon[f"{(i + 1) * frame_period_s:g}s"] = stats(dxy[:, :, i], both[:, :, i])
    return {"xy_m": stats(dxy, both), "xy_m_by_horizon": per_horizon, "heading_rad": stats(dh, both),
            "valid_agree": float((np.asarray(a.valid)[:, :, h:] == np.asarray(b.valid)[:, :, h:]).mean()),
            "map_token_agree": float((np.asarray(a.map_tokens)[:, :, h:] == np.asarray(b.map_tokens)[:, :, h:]).mean()),
            "agent_slots_compared": int(both.sum())}


def _from_log(out, view, h: int) -> float | None:
    """Mean distance (m) of rolled-out agents ([B, 1, T, A, ...]) from the log over the generated frames, slots valid
    in both."""
    both = np.asarray(out.valid)[:, 0, h:] & np.asarray(view.valid)[:, h:]
    d = np.linalg.norm(np.asarray(out.xy)[:, 0, h:] - np.asarray(view.xy)[:, h:], axis=-1)
    return float(d[both].mean()) if both.any() else None


def bench_precision(args) -> dict:
    """A shipped model's rollouts of stored scenes under every task with a float32 and a bfloat16 KV cache and decode
    attention (this backend's fastest attention for each: `auto`), and how far apart they are
    (`precision_differences`)."""
    import gpd_jax

    model = gpd_jax.load_model(args.model)
    idx = range(args.scenarios) if args.scenarios else None
    scenes = gpd_jax.load_scenes(args.data, args.split, indices=idx)
    n = scenes.xy.shape[0]
    outs = {}
    for dtype in ("float32", "bfloat16"):
        m = model.with_decode(dtype=dtype)
        parts = []
        for lo in range(0, n, args.batch):
            part = jax.tree.map(lambda x: x[lo:lo + args.batch], scenes)
            out = jax.block_until_ready(gpd_jax.rollout(m, part, "all", jax.random.key(0)))
            parts.append(jax.device_get(out))
        outs[dtype] = jax.tree.map(lambda *x: np.concatenate(x, 0), *parts)
    spec = model.spec
    view = model.prepare(scenes)
    diff = {"all": precision_differences(outs["float32"], outs["bfloat16"], spec.num_history, spec.frame_period_s)}
    for k, name in enumerate(TASK_NAMES):
        pick = lambda o: jax.tree.map(lambda x: x[:, k:k + 1], o)
        diff[name] = precision_differences(pick(outs["float32"]), pick(outs["bfloat16"]), spec.num_history,
                                           spec.frame_period_s)
        # what the difference does to a figure: the mean distance of the rolled-out agents from the log
        diff[name]["from_log_m"] = {dt: _from_log(pick(o), view, spec.num_history) for dt, o in outs.items()}
    return {"machine": device_info(), "model": args.model or "default", "data": f"{args.data}:{args.split}",
            "scenarios": n, "tasks": list(TASK_NAMES), "future_s": (spec.num_frames - spec.num_history)
            * spec.frame_period_s, "bfloat16_vs_float32": diff}


def _print_table(out: dict) -> None:
    mc = out.get("machine", {})
    print(f"machine: {mc.get('cpu')} ({mc.get('isa')}, {mc.get('usable_cores')} cores), jax {mc.get('jax')}, "
          f"backend {mc.get('backend')}")
    print(f"peaks: matmul fp32 {out['matmul_gflops']:.1f} GFLOP/s, bf16 {out['matmul_bf16_gflops']:.1f} GFLOP/s, "
          f"copy {out['copy_gbps']:.1f} GB/s; cached rollout: {out['rollout_gflop_per_scenario']:.1f} GFLOP per "
          "scenario")
    head = ("config", "attention", "dtype", "batch", "future", "cached s/scn", "recompute s/scn", "speedup",
            "compile s", "GFLOP/s", "of matmul", "GB/s", "of copy", "KV cache MiB/scn", "peak MiB/scn")
    print(" | ".join(head))
    for r in out["runs"]:
        rec = "-" if r["recompute_s_per_scenario"] is None else f"{r['recompute_s_per_scenario']:.2f}"
        sp = "-" if r["speedup"] is None else f"{r['speedup']:.1f}x"
        peak = r["memory"].get("peak_bytes_per_scenario")
        print(" | ".join([r["config"], r["decode_attention"], r["decode_dtype"], str(r["batch"]),
                          str(r["future_frames"]), f"{r['cached_s_per_scenario']:.4f}", rec, sp,
                          f"{r['compile_s']:.1f}", f"{r['achieved_gflops']:.1f}", f"{r['achieved_over_matmul']:.2f}",
                          f"{r['achieved_gbps']:.1f}", f"{r['achieved_over_copy']:.2f}",
                          f"{r['kv_cache_bytes_per_scenario'] / 2**20:.1f}",
                          "-" if peak is None else f"{peak / 2**20:.1f}"]))
        if r["workload"]:
            w = r["workload"]
            print(f"  {w['scenarios']} scenarios x {w['tasks']} tasks: {w['seconds']:.2f} s in {w['calls']} calls "
                  f"of batch {w['batch']} (compile {w['compile_s']:.1f} s, excluded)")
    for kernel in dict.fromkeys((r["decode_attention"], r["decode_dtype"]) for r in out["runs"]):
        runs = [r for r in out["runs"] if (r["decode_attention"], r["decode_dtype"]) == kernel]
        for r in runs[1:]:
            print(f"{'/'.join(kernel)}: batch {r['batch']} throughput per scenario = "
                  f"{runs[0]['cached_s_per_scenario'] / r['cached_s_per_scenario']:.2f}x batch {runs[0]['batch']}")
    for r in out["runs"]:
        for c in r.get("auto_choices") or []:
            print(f"batch {r['batch']} {r['decode_attention']}: auto chose {c['choice']} ({c['source']}): {c['why']}")
    if "recompute_method" in out:
        print(f"recompute: {out['recompute_method']}")


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    overrides, rest = split_config_args(argv)
    p = ArgumentParser(prog=program("python -m gpd_jax.bench"), description=__doc__.split("\n\n")[0])
    sub = p.add_subparsers(dest="what", required=True)
    r = sub.add_parser("rollout", help="cached vs recompute rollout speed")
    r.add_argument("--config", default="configs/gpd_paper.py")
    r.add_argument("--batch", type=count, nargs="+", default=[1, 16])
    r.add_argument("--future-frames", type=count, default=None, help="default: all (num_frames - num_history)")
    r.add_argument("--recompute-points", type=count0, default=5,
                   help="prefix lengths at which to time the recompute forward (0: time the whole rollout)")
    r.add_argument("--repeats", type=count, default=3)
    r.add_argument("--matmul-size", type=count, default=4096)
    r.add_argument("--copy-mib", type=count, default=256, help="size of the copy that measures memory bandwidth")
    r.add_argument("--decode-dtype", nargs="+", choices=DECODE_DTYPES, default=None,
                   help="KV cache / decode attention dtype(s), each measured with every kernel and batch "
                        "(default: the config's model.decode_dtype)")
    r.add_argument("--workload", type=count, default=None, metavar="SCENARIOS",
                   help="also time SCENARIOS scenarios x 6 tasks in calls of the largest batch (compile excluded)")
    r.add_argument("--devices", type=count, default=None,
                   help="shard each batch over this many devices (default: all, of every process; on a CPU one per "
                        "core)")
    r.add_argument("--decode-attention", nargs="+", choices=KERNELS, default=None,
                   help="attention kernel(s) of the cached rollout, each measured at every batch size "
                        "(default: the config's model.decode_attention)")
    r.add_argument("--native-march", nargs="+", default=None,
                   help="build target(s) of the native kernel (gcc -march), each measured with native and auto "
                        "(default: $GPD_JAX_NATIVE_MARCH or native); e.g. native x86-64-v3")
    r.add_argument("--json", type=output_file, default=None, help="write the results here")
    distributed.add_arguments(r)  # each batch over every process's devices; process 0 prints and writes
    q = sub.add_parser("realism", help="seconds per scenario of the WOSAC-form realism metric")
    q.add_argument("--data", default=None, help="a store with road geometry (default: synthetic scenes and roads)")
    q.add_argument("--split", default="test")
    q.add_argument("--rollouts", type=count, default=32)
    q.add_argument("--agents", type=count, default=32)
    q.add_argument("--scenarios", type=count, default=8, help="scenarios per compiled batch")
    q.add_argument("--realism-config", choices=("2024", "2025"), default="2025")
    q.add_argument("--skip", type=int, default=0, help="scenes of the split to skip before the --scenarios timed")
    q.add_argument("--no-signals", action="store_true",
                   help="leave the traffic-light term out where the store has signal states (2025 scores it)")
    q.add_argument("--rules", nargs="+", choices=("official", "corrected"), default=["official", "corrected"],
                   help="the counting rules to time, each compiled on its own (default: both)")
    q.add_argument("--export-official", default=None, type=output_file, metavar="NPZ",
                   help="also write the scenes and rollouts for tests/conformance/run_official.py")
    q.add_argument("--repeats", type=count, default=3)
    q.add_argument("--json", type=output_file, default=None, help="write the results here")

    c = sub.add_parser("precision", help="a shipped model's rollouts with a bfloat16 vs a float32 KV cache")
    c.add_argument("--data", required=True, help="a store of held-out scenes")
    c.add_argument("--split", default="test")
    c.add_argument("--model", default=None, help="a shipped model's name or a folder (default: the default model)")
    c.add_argument("--scenarios", type=count, default=None, help="the first N scenes (default: all)")
    c.add_argument("--batch", type=count, default=40, help="scenes per rollout call")
    c.add_argument("--json", type=output_file, default=None, help="write the results here")

    g = sub.add_parser("samples", help="K sampled futures per scene in one compiled rollout: time and memory")
    g.add_argument("--model", default="gpd_sampling", help="a shipped model's name or a folder")
    g.add_argument("--data", required=True, help="a store of scenes")
    g.add_argument("--split", default="test")
    g.add_argument("--samples", type=count, default=32)
    g.add_argument("--scenarios", type=count, default=4, help="scenes in the one compiled call")
    g.add_argument("--tasks", nargs="+", default=["traffic_simulation"], choices=TASK_NAMES)
    g.add_argument("--temperature", type=nonnegative, default=1.0)
    g.add_argument("--repeats", type=count, default=3)
    g.add_argument("--json", type=output_file, default=None, help="write the results here")

    def work():
        args = p.parse_args(rest)
        if overrides and args.what != "rollout":
            raise UsageError(f"python -m gpd_jax.bench {args.what} takes no --config.* overrides")
        if args.what == "samples":
            out = bench_samples(args)
            mem = out["memory"]
            print(f"{out['model']}: {out['scenarios']} scenes x {len(out['tasks'])} task(s) x {out['samples']} "
                  f"samples = {out['rollouts']} rollouts in one call ({out['source']}; backend "
                  f"{out['machine']['backend']}): {out['s_per_scenario']:.3f} s per scene, "
                  f"{out['s_per_rollout'] * 1e3:.2f} ms per rollout (compile {out['compile_s']:.1f} s)")
            print(f"KV cache: {out['kv_cache_bytes_per_rollout'] / 2**20:.2f} MiB per rollout, "
                  f"{out['kv_cache_bytes_per_scenario'] / 2**20:.1f} MiB per scene at K = {out['samples']}; "
                  f"compiled peak {mem.get('peak_bytes_per_scenario', float('nan')) / 2**20:.1f} MiB per scene; "
                  f"spread of the samples {out['sample_spread_m']:.2f} m")
        elif args.what == "precision":
            out = bench_precision(args)
            print(f"{out['model']} on {out['data']} ({out['scenarios']} scenes x {len(out['tasks'])} tasks, "
                  f"{out['future_s']:g} s; backend {out['machine']['backend']}): bfloat16 vs float32")
            print("task | xy mean m | xy p99 m | xy max m | heading p99 rad | valid agree | map tokens agree | "
                  "from the log, m: float32 / bfloat16")
            num = lambda x: "-" if x is None else f"{x:.2e}"
            for name, d in out["bfloat16_vs_float32"].items():
                fl = d.get("from_log_m")
                print(" | ".join([name, *(num(d["xy_m"][k]) for k in ("mean", "p99", "max")),
                                  num(d["heading_rad"]["p99"]), f"{d['valid_agree']:.4f}",
                                  f"{d['map_token_agree']:.4f}",
                                  "-" if fl is None else f"{fl['float32']:.4f} / {fl['bfloat16']:.4f}"]))
        elif args.what == "realism":
            out = bench_realism(args)
            mc = out["machine"]
            print(f"machine: {mc.get('cpu')} ({mc.get('usable_cores')} cores), jax {mc.get('jax')}, "
                  f"backend {mc.get('backend')}; {out['source']}")
            for rules, r in out["rules"].items():
                print(f"realism ({out['config']}, {rules} rules): {out['rollouts']} rollouts x "
                      f"{out['future_frames']} frames x {out['agents']} agents, {out['scenarios']} scenarios per "
                      f"call: {r['s_per_scenario']:.3f} s per scenario (compile {r['compile_s']:.1f} s); "
                      f"road-edge answers not proven exact: {r['road_edge_inexact_share']:.2%}; traffic lights "
                      + ("scored" if out["traffic_lights"] else "not scored"))
        else:
            cluster = distributed.from_args(args)
            parallel.use_host_cores()
            distributed.initialize(cluster)
            out = bench_rollout(args, overrides)
            if not distributed.is_lead():  # process 0 prints and writes the figures of the whole mesh
                return
            _print_table(out)
        if args.json:
            atomic_write_json(args.json, out, indent=2)
            print(f"wrote {args.json}")

    return run_command("python -m gpd_jax.bench", work, (FileNotFoundError, ValueError, KeyError))


if __name__ == "__main__":
    sys.exit(main())
