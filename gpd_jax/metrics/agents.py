"""Agent metrics at fixed horizons: ADE, FDE and collision rate for the ego (slot 0) and the agents (slots 1..).

Two variants, selected by `variant`:

* ``"paper"`` — the official GPD-1 code's definitions, quirks included (`reference/gpd_official.md` §6):
  - N_exist = agents valid (in the log) in *any* future frame of the window passed in (the ego: one per scenario);
  - ADE@H = mean over the first H future steps of ADE[t], ADE[t] = sum_agents ||p^ - p|| * m_t / N_exist;
  - FDE@H = sum over agents of the error at the agent's last valid log frame within the first H steps / N_exist;
  - collision@H = the paper's definition (appendix: "the proportion of agents that experienced at least one
    collision during the evaluation period relative to the total number of interacting agents"): entities with
    at least one colliding step among the first H / N_exist, in percent. At step t every entity visible in the log
    gets a fixed 4.084 x 1.85 m box at its *predicted* pose (the ego too) and entities are tested pairwise with
    the separating-axis test.
  - collision_frames@H = the official code's per-frame rate: mean over the first H steps of (# colliding
    entities at t) / N_exist, in percent (reads lower than the paper's definition: a collision lasting one
    frame of H counts 1/H).
* ``"corrected"`` — the same quantities normalised properly:
  - ADE@H = mean error over valid (agent, t) pairs, t < H;
  - FDE@H = mean over agents valid somewhere in the first H steps of the error at their last valid frame there;
  - collision@H = entities with at least one colliding step among the first H / entities present in at least
    one of them, in percent, where an entity is present at t when it is valid in the log and in the prediction,
    boxes have each agent's own (length, width), and an entity only collides with other present entities;
  - collision_frames@H = colliding (entity, t) pairs / present (entity, t) pairs, t < H, in percent.

Both variants are computed as sums and counts (`agent_metric_sums`, summed over every leading batch dim), which add
up exactly across batches (`accumulate`) and are turned into the numbers by `reduce_agent_metrics`. Positions are
box centres for every slot (the official code puts the ego box at the rear axle; our scenes store box centres).

**Split by motion at the current frame** (optional, `current_speed=`): ADE and FDE are also summed separately for
entities *stationary* (speed < `STATIONARY_MPS` = 0.5 m/s), *moving* (>= 0.5 m/s) and of unknown speed (NaN: no
velocity measured, e.g. first seen at the current frame), with the same numerators and denominators as the
unsplit metric restricted to each class (the paper variant's N_exist too), so the three classes' sums add up to
the unsplit sums exactly; `{g}_n_{class}` counts the entities of a class with a valid log frame within the
horizon.

**Along- and cross-track error of moving entities** (optional, `current_direction=` with `current_speed=`): the
error vector of each moving entity at every frame split into its component along the direction of motion at the
current frame and the one across it, |e . u| and |e x u| (u the unit direction), summed as ADE and FDE with the
moving class's denominators ("{g}_{ade,fde}_{along,cross}_moving"). Along-track error is speed: braking,
starting, the wrong pace; cross-track error is the path: turns, curves, lane changes that the direction at the
current frame does not continue.
"""

from __future__ import annotations

from typing import Any, Sequence

import jax
import jax.numpy as jnp
import numpy as np

# The official collision checker's fixed box (length, width) in metres.
PAPER_BOX = (4.084, 1.85)
DEFAULT_HORIZONS = (30, 50, 80)  # future frames at 10 Hz: 3, 5, 8 s
VARIANTS = ("paper", "corrected")
_NAMES = ("ade", "fde", "collision", "collision_frames")
_RATES = ("collision", "collision_frames")  # reported in percent
# Motion at the current frame (the optional split of ADE / FDE): speed below this (m/s) is stationary.
STATIONARY_MPS = 0.5
MOTION_CLASSES = ("stationary", "moving", "speed_unknown")
_SPLIT_NAMES = ("ade", "fde")
TRACK_COMPONENTS = ("along", "cross")  # of moving entities' errors, against the current direction of motion


def horizon_label(frames: int, dt: float = 0.1) -> str:
    """'3s' for 30 frames at 10 Hz."""
    return f"{frames * dt:g}s"


# --------------------------------------------------------------------------------------------- box overlap
def box_corners(xy: jax.Array, heading: jax.Array, size: jax.Array) -> jax.Array:
    """Corners of oriented boxes.

    Args:
      xy: f32[..., 2] box centres; heading: f32[...]; size: f32[..., 2] (length, width).

    Returns:
      f32[..., 4, 2] corners, counter-clockwise: front-left, rear-left, rear-right, front-right.
    """
    c, s = jnp.cos(heading), jnp.sin(heading)
    fwd = jnp.stack([c, s], -1) * (size[..., 0:1] / 2)
    left = jnp.stack([-s, c], -1) * (size[..., 1:2] / 2)
    signs = jnp.array([[1, 1], [-1, 1], [-1, -1], [1, -1]], xy.dtype)
    return xy[..., None, :] + signs[:, 0:1] * fwd[..., None, :] + signs[:, 1:2] * left[..., None, :]


@jax.jit
def box_overlap_pairwise(xy: jax.Array, heading: jax.Array, size: jax.Array,
                         valid: jax.Array | None = None) -> jax.Array:
    """Pairwise oriented-box overlap by the separating-axis test.

    Args:
      xy: f32[..., N, 2] box centres; heading: f32[..., N]; size: f32[..., N, 2] (length, width), or f32[2] for one
        size shared by all boxes; valid: optional bool[..., N] (invalid boxes overlap nothing).

    Returns:
      bool[..., N, N], symmetric, False on the diagonal; True where the boxes' interiors intersect (boxes that only
      touch along an edge do not overlap).
    """
    size = jnp.broadcast_to(size, xy.shape).astype(xy.dtype)
    half = size / 2
    u = jnp.stack([jnp.cos(heading), jnp.sin(heading)], -1)  # [..., N, 2] long axis
    v = jnp.stack([-jnp.sin(heading), jnp.cos(heading)], -1)  # lateral axis
    axes_own = jnp.stack([u, v], -2)  # [..., N, 2 axes, 2]
    d = xy[..., None, :, :] - xy[..., :, None, :]  # [..., i, j, 2] centre of j minus centre of i

    def radius(axis, k):  # projected half extent of box k on `axis` [..., i, j, 2 axes, 2]
        uk = jnp.expand_dims(u, k)[..., None, :]
        vk = jnp.expand_dims(v, k)[..., None, :]
        hk = jnp.expand_dims(half, k)[..., None, :]
        return hk[..., 0] * jnp.abs(jnp.sum(axis * uk, -1)) + hk[..., 1] * jnp.abs(jnp.sum(axis * vk, -1))

    def separated_on(axes):  # axes [..., i, j, 2, 2] -> any separating axis among them [..., i, j]
        gap = jnp.abs(jnp.sum(axes * d[..., None, :], -1))
        # box i varies along dim -2 of the [i, j] grid, box j along dim -1; expand the other one.
        return jnp.any(gap >= radius(axes, -2) + radius(axes, -3), -1)

    n = xy.shape[-2]
    axes_i = jnp.broadcast_to(axes_own[..., :, None, :, :], xy.shape[:-2] + (n, n, 2, 2))
    axes_j = jnp.broadcast_to(axes_own[..., None, :, :, :], xy.shape[:-2] + (n, n, 2, 2))
    overlap = ~(separated_on(axes_i) | separated_on(axes_j))
    overlap = overlap & ~jnp.eye(n, dtype=bool)
    if valid is not None:
        overlap = overlap & valid[..., :, None] & valid[..., None, :]
    return overlap


# --------------------------------------------------------------------------------------------- sums
def agent_metric_sums(pred_xy: jax.Array, pred_heading: jax.Array, gt_xy: jax.Array, gt_valid: jax.Array,
                      size: jax.Array, *, num_history: int = 0, pred_valid: jax.Array | None = None,
                      eval_mask: jax.Array | None = None, horizons: Sequence[int] = DEFAULT_HORIZONS,
                      variant: str = "paper", dt: float = 0.1, current_speed: jax.Array | None = None,
                      stationary_below: float = STATIONARY_MPS, current_direction: jax.Array | None = None
                      ) -> dict[str, dict[str, jax.Array]]:
    """Sums and counts of the ADE / FDE / collision metrics, summed over every leading batch dim.

    Args:
      pred_xy: f32[..., T, A, 2] predicted box centres (a rollout's or baseline's output; slot 0 is the ego).
      pred_heading: f32[..., T, A] predicted headings.
      gt_xy: f32[..., T, A, 2] logged box centres.
      gt_valid: bool[..., T, A] logged validity (which (agent, t) exist in the ground truth).
      size: f32[..., A, 2] logged box (length, width) per slot (used by "corrected" collisions only).
      num_history: frames [0, num_history) are history and ignored; the future starts at frame num_history.
        Pass the whole future (80 frames in the paper) even for shorter horizons: the paper's N_exist counts
        agents valid anywhere in the future window.
      pred_valid: optional bool[..., T, A] predicted validity (corrected collisions only; defaults to gt_valid).
      eval_mask: optional bool[..., A] which slots are scored (e.g. only generated agents); all others still
        take part in collisions as obstacles. Defaults to all slots.
      horizons: future frame counts, each <= T - num_history.
      variant: "paper" or "corrected" (see module docstring).
      dt: frame period in seconds (for the horizon labels only).
      current_speed: optional f32[..., A] each slot's speed (m/s) at the current frame, NaN where unknown: adds
        the ADE / FDE sums split by motion class (`MOTION_CLASSES`, module docstring).
      stationary_below: the speed (m/s) below which a slot is stationary.
      current_direction: optional f32[..., A, 2] each slot's unit direction of motion at the current frame (only
        read for moving slots; needs `current_speed`): adds the along- and cross-track ADE / FDE sums of the
        moving class (module docstring).

    Returns:
      {horizon_label: {"{ego,agent}_{ade,fde,collision,collision_frames}_{num,den}": f32[]}}; with
      `current_speed` also "{ego,agent}_{ade,fde}_{class}_{num,den}" and "{ego,agent}_n_{class}" for every class
      of `MOTION_CLASSES`; with `current_direction` also "{g}_{ade,fde}_{along,cross}_moving_num". Feed to
      `reduce_agent_metrics`.
    """
    rows = agent_sum_rows(horizons, variant, dt, current_speed is not None, current_direction is not None)
    return name_agent_sums(agent_sum_table(
        pred_xy, pred_heading, gt_xy, gt_valid, size, num_history=num_history, pred_valid=pred_valid,
        eval_mask=eval_mask, horizons=horizons, variant=variant, dt=dt, current_speed=current_speed,
        stationary_below=stationary_below, current_direction=current_direction), rows)


def _paper_or_corrected(variant: str, paper, corrected):
    return paper if variant == "paper" else corrected


def agent_sum_rows(horizons: Sequence[int], variant: str, dt: float = 0.1, split: bool = False,
                   track: bool = False) -> tuple[tuple[str, str, str, int, int], ...]:
    """What each entry of `agent_sum_table` is: (horizon label, key of `agent_metric_sums`, the sum it is,
    selection set, horizon index), in the order of `agent_metric_sums`' keys. The sums are the per-set and
    per-horizon quantities of `agent_sum_table`; the sets are ego and agents (0, 1) and, with `split`, each
    group's motion classes (2 + 3 * group + class). `track`: the along- / cross-track sums of the moving class."""
    rows = []
    for hi, h in enumerate(horizons):
        hl = horizon_label(h, dt)
        for gi, g in enumerate(("ego", "agent")):
            src = _paper_or_corrected(
                variant,
                {"ade_num": "err", "ade_den": "exist_h", "fde_num": "fde", "fde_den": "exist", "collision_num": "col",
                 "collision_den": "exist", "collision_frames_num": "colf", "collision_frames_den": "exist_h"},
                {"ade_num": "err", "ade_den": "cnt", "fde_num": "fde", "fde_den": "anyv", "collision_num": "col",
                 "collision_den": "col_den", "collision_frames_num": "colf", "collision_frames_den": "colf_den"})
            rows += [(hl, f"{g}_{n}", q, gi, hi) for n, q in src.items()]
            if not split:
                continue
            for ki, k in enumerate(MOTION_CLASSES):
                si = 2 + 3 * gi + ki
                rows += [(hl, f"{g}_ade_{k}_num", "err", si, hi), (hl, f"{g}_n_{k}", "anyv", si, hi),
                         (hl, f"{g}_ade_{k}_den", _paper_or_corrected(variant, "exist_h", "cnt"), si, hi),
                         (hl, f"{g}_fde_{k}_num", "fde", si, hi),
                         (hl, f"{g}_fde_{k}_den", _paper_or_corrected(variant, "exist", "anyv"), si, hi)]
                if k == "moving" and track:
                    for comp in TRACK_COMPONENTS:
                        rows += [(hl, f"{g}_ade_{comp}_moving_num", f"{comp}_err", si, hi),
                                 (hl, f"{g}_fde_{comp}_moving_num", f"{comp}_fde", si, hi)]
    return tuple(rows)


def name_agent_sums(table, rows) -> dict[str, dict[str, Any]]:
    """`agent_sum_table`'s f32[..., R] (any leading dims: jax or numpy) -> `agent_metric_sums`' dict
    {horizon label: {key: [...]}} (`rows`: `agent_sum_rows`)."""
    out: dict[str, dict[str, Any]] = {}
    for i, (hl, key, *_) in enumerate(rows):
        out.setdefault(hl, {})[key] = table[..., i]
    return out


def agent_sum_table(pred_xy: jax.Array, pred_heading: jax.Array, gt_xy: jax.Array, gt_valid: jax.Array,
                    size: jax.Array, *, num_history: int = 0, pred_valid: jax.Array | None = None,
                    eval_mask: jax.Array | None = None, horizons: Sequence[int] = DEFAULT_HORIZONS,
                    variant: str = "paper", dt: float = 0.1, current_speed: jax.Array | None = None,
                    stationary_below: float = STATIONARY_MPS, current_direction: jax.Array | None = None
                    ) -> jax.Array:
    """`agent_metric_sums` as one array f32[R]: entry r is the sum `agent_sum_rows(...)[r]` names (same
    arguments). Every sum of every horizon and selection set comes from a dozen masked reductions over
    [set, horizon, ..., frame, slot] instead of one reduction per key, horizon and set (hundreds of kernels, the
    compile time of the evaluation), and one gather picks the entries; `name_agent_sums` names them (on the
    host, after the compiled call, it adds no kernels)."""
    if variant not in VARIANTS:
        raise ValueError(f"variant must be one of {VARIANTS}, got {variant!r}")
    if current_direction is not None and current_speed is None:
        raise ValueError("current_direction splits the moving class's errors: pass current_speed too")
    horizons = tuple(horizons)
    t_total = gt_xy.shape[-3]
    fut = t_total - num_history
    if max(horizons) > fut:
        raise ValueError(f"horizon {max(horizons)} frames exceeds the {fut} future frames given (frames at another "
                         "rate? pass a model's frames with horizons and dt, or agent_metrics(..., spec=model.spec))")
    sl = lambda a, axis: jax.lax.slice_in_dim(a, num_history, t_total, axis=a.ndim + axis)  # noqa: E731
    pxy, ph, gxy, gv = sl(pred_xy, -3), sl(pred_heading, -2), sl(gt_xy, -3), sl(gt_valid, -2)
    pv = gv if pred_valid is None else sl(pred_valid, -2)
    a = gxy.shape[-2]
    batch = gxy.shape[:-3]
    nb = len(batch)
    ev = jnp.ones(batch + (a,), bool) if eval_mask is None else jnp.broadcast_to(eval_mask, batch + (a,))
    is_ego = jnp.arange(a) == 0
    sets = [ev & is_ego, ev & ~is_ego]  # [..., A]: ego, agents
    if current_speed is not None:
        speed = jnp.broadcast_to(current_speed, batch + (a,))
        known = ~jnp.isnan(speed)
        classes = (known & (speed < stationary_below), known & (speed >= stationary_below), ~known)
        sets += [g & k for g in sets[:2] for k in classes]  # each group's MOTION_CLASSES, a partition of it
    sel = jnp.stack(sets)  # [S, ..., A]

    evec = pxy - gxy  # [..., F, A, 2]
    err = jnp.where(gv, jnp.linalg.norm(evec, axis=-1), 0.0)  # [..., F, A]
    if variant == "paper":
        collide = jnp.any(box_overlap_pairwise(pxy, ph, jnp.array(PAPER_BOX, pxy.dtype), gv), -1)  # [..., F, A]
        q = gv  # where a collision counts
    else:
        q = gv & pv  # present: valid in the log and in the prediction
        own = box_overlap_pairwise(pxy, ph, jnp.broadcast_to(size[..., None, :, :], pxy.shape), q)
        collide = jnp.any(own, -1) & q

    f = gxy.shape[-3]
    hmask = jnp.arange(f)[None, :] < jnp.array(horizons)[:, None]  # [Hn, F]
    # [S or 1, Hn or 1, ..., F or 1, A] layouts: sets lead, then horizons, then the batch, frames and slots
    per_set = lambda x: x[:, None, ..., None, :]  # noqa: E731  [S, ..., A] -> [S, 1, ..., 1, A]
    per_h = lambda x: x[None]  # noqa: E731  [Hn, ..., A] -> [1, Hn, ..., A]
    hm = hmask.reshape((1, len(horizons)) + (1,) * nb + (f, 1))  # [1, Hn, 1.., F, 1]
    total = lambda x: jnp.sum(x.astype(jnp.float32), axis=tuple(range(2, x.ndim)))  # noqa: E731  -> [S, Hn]
    sm = per_set(sel)
    mh = hm & gv[None, None]  # valid within the horizon [1, Hn, ..., F, A]

    last = jnp.max(jnp.where(mh, jnp.arange(f)[:, None], -1), axis=-2)[0]  # [Hn, ..., A] last valid frame, or -1
    any_valid = last >= 0

    def last_valid(x):  # [..., F, A] -> the value at the last valid frame within each horizon (0 if none) [Hn, ..., A]
        v = jnp.take_along_axis(jnp.broadcast_to(x, last.shape[:1] + x.shape), jnp.maximum(last, 0)[..., None, :],
                                axis=-2)[..., 0, :]
        return jnp.where(any_valid, v, 0.0)

    fde_err = last_valid(err)
    sm_h = sm[..., 0, :]  # [S, 1, ..., A]
    qs = {"err": jnp.where(sm & mh, err, 0.0), "fde": jnp.where(sm_h, per_h(fde_err), 0.0),
          "anyv": sm_h & per_h(any_valid), "colf": sm & hm & collide & q,
          "col": sm_h & jnp.any(hm & collide & q, axis=-2)}
    shape = (sel.shape[0], len(horizons))
    sums = {}  # [S, Hn] sums that are not a reduction of their own
    if variant == "paper":
        exists = jnp.any(gv, axis=-2) | is_ego  # [..., A]: the ego counts once per scenario, as the official code
        n_exist = total(sm_h & exists)  # [S, 1]
        sums["exist"] = jnp.broadcast_to(n_exist, shape)
        sums["exist_h"] = jnp.array(horizons, jnp.float32)[None] * n_exist
    else:
        qs["cnt"] = sm & mh
        qs["col_den"] = sm_h & jnp.any(hm & q, axis=-2)
        qs["colf_den"] = sm & hm & q
    if current_direction is not None:
        u = jnp.broadcast_to(current_direction, batch + (a, 2))[..., None, :, :]  # [..., 1, A, 2]
        track = {"along": jnp.abs(jnp.sum(evec * u, -1)),
                 "cross": jnp.abs(evec[..., 0] * u[..., 1] - evec[..., 1] * u[..., 0])}
        for comp, te in track.items():
            te = jnp.where(gv, te, 0.0)  # [..., F, A]
            qs[f"{comp}_err"] = jnp.where(sm & mh, te, 0.0)
            qs[f"{comp}_fde"] = jnp.where(sm_h, per_h(last_valid(te)), 0.0)
    sums.update({k: total(v) for k, v in qs.items()})
    names = sorted(sums)
    table = jnp.stack([sums[k] for k in names])  # [sums, S, Hn]
    rows = agent_sum_rows(horizons, variant, dt, current_speed is not None, current_direction is not None)
    idx = np.array([(names.index(src), si, hi) for _, _, src, si, hi in rows])
    return table[idx[:, 0], idx[:, 1], idx[:, 2]]


def accumulate(a, b):
    """Adds two sums pytrees (from `agent_metric_sums` or `map_metric_sums`); `a` may be None."""
    return b if a is None else jax.tree.map(jnp.add, a, b)


def reduce_agent_metrics(sums: dict[str, dict[str, jax.Array]]) -> dict[str, dict[str, float]]:
    """Sums -> {horizon_label: {ego_ade, ego_fde, ego_collision, ego_collision_frames, agent_ade, ...}}.

    With the motion split (`current_speed` given to `agent_metric_sums`) also "{g}_{ade,fde}_{class}" and the
    count "{g}_n_{class}" for every class of `MOTION_CLASSES`; with `current_direction` also the moving class's
    "{g}_{ade,fde}_{along,cross}_moving".

    ADE / FDE in metres, collision rates in percent; NaN where the denominator is 0 (nothing to score).
    """
    out = {}
    ratio = lambda num, den: float(num) / float(den) if float(den) > 0 else float("nan")
    for hl, d in sums.items():
        r = {}
        for g in ("ego", "agent"):
            for n in _NAMES:
                v = ratio(d[f"{g}_{n}_num"], d[f"{g}_{n}_den"])
                r[f"{g}_{n}"] = 100.0 * v if n in _RATES else v
            for k in MOTION_CLASSES:
                if f"{g}_n_{k}" not in d:
                    continue
                for n in _SPLIT_NAMES:
                    r[f"{g}_{n}_{k}"] = ratio(d[f"{g}_{n}_{k}_num"], d[f"{g}_{n}_{k}_den"])
                r[f"{g}_n_{k}"] = int(round(float(d[f"{g}_n_{k}"])))
            for n in _SPLIT_NAMES:
                for comp in TRACK_COMPONENTS:
                    if f"{g}_{n}_{comp}_moving_num" in d:
                        r[f"{g}_{n}_{comp}_moving"] = ratio(d[f"{g}_{n}_{comp}_moving_num"], d[f"{g}_{n}_moving_den"])
        out[hl] = r
    return out


_STATIC = ("num_history", "horizons", "variant", "dt", "stationary_below")
_agent_metric_sums_jit = jax.jit(agent_metric_sums, static_argnames=_STATIC)


def agent_metrics(*args, spec=None, **kwargs) -> dict[str, dict[str, float]]:
    """`reduce_agent_metrics(agent_metric_sums(...))` for one batch (same arguments as `agent_metric_sums`), jitted.

    spec: a model's `ModelSpec` (`model.spec`) to score a rollout of that model at its frame rate: it sets
    `num_history`, `horizons` (3 / 5 / 8 s as the model's frames) and `dt` unless they are given.

        out = gpd_jax.rollout(model, scenes, "traffic_simulation")
        view = model.prepare(scenes)
        gpd_jax.metrics.agent_metrics(out.xy, out.heading, view.xy, view.valid, view.size, spec=model.spec)
    """
    if spec is not None:
        kwargs.setdefault("num_history", spec.num_history)
        kwargs.setdefault("horizons", spec.horizons)
        kwargs.setdefault("dt", spec.frame_period_s)
    if "horizons" in kwargs:
        kwargs["horizons"] = tuple(kwargs["horizons"])
    return reduce_agent_metrics(_agent_metric_sums_jit(*args, **kwargs))
