"""Prompts: conditional generation beyond the six named tasks (the paper's §3.4 "Conditional Generation").

A `Prompt` says, for every frame and every token slot (map slots first, then ego, then agents), whether the
rollout takes the token from the *given data* or from the model, and what the given data is:

* the log of the scene, overridden where the prompt gives agent states (`agent_given`: in-painted paths, given
  initial trajectories, absent agents) or map tokens (`map_given`);
* optionally a vector map of its own (`lanes`: polylines in the scene frame), rasterized and encoded into map
  tokens around the ego of every frame inside the compiled rollout (the map tokenizer's `pose_encoder`), for the
  map slots that are taken from the given data, history included;
* agents hidden in every frame, and a cap on the number of agent slots (slots >= `max_agents` are invalid in
  every frame, generated ones included).

A `Task` is the special case whose mask is the same at every future frame and which gives nothing beyond the log
(`as_prompt`): a task and its prompt roll out to identical arrays. Since a prompt is arrays, one compiled rollout
runs a batch that mixes prompts (`stack_prompts` gives them one pytree structure).

Builders (numpy, host side): `prompt_from_task` (a task name), `make_prompt` (a scene plus per-agent and
per-frame choices: given paths over chosen frames, the log until frame k, given initial trajectories for a subset
of slots, an agent cap, hidden agents, a lane list, given map tokens) and `prompt_from_json` (the command line's
prompt file, see examples/prompt_inpaint.json; every problem raises `PromptError` naming the field).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

import flax.struct
import jax
import numpy as np

from gpd_jax.scene import Scene
from gpd_jax.tasks import TASK_NAMES, TASKS, Task

LANE_SPACING_M = 1.0  # given lanes are resampled to at most this spacing (the tokenizer's max_segment_length)


class PromptError(ValueError):
    """A prompt that cannot be built; the message names the field (and the JSON path, for a file)."""


@flax.struct.dataclass
class Prompt:
    """What a rollout is given, per frame and slot (or a batch of prompts: leading dims `...`).

    from_log: bool[..., T, M + A] whether frame t's slot comes from the given data (True) or the model. Frames
      before num_history are always given (the history); their rows are not read.
    hidden: bool[..., A] agents removed (invalid) in every frame, history included.
    max_agents: i32[...] agent cap: slots >= max_agents are invalid in every frame (ego = slot 0 counts).
    agent_given: optional bool[..., T, A] where `xy`, `heading`, `valid` replace the log's agent states.
    xy: optional f32[..., T, A, 2], heading: optional f32[..., T, A], valid: optional bool[..., T, A] the given
      agent states (read where agent_given). Velocities of given states are their backward differences.
    map_given: optional bool[..., T] frames whose map tokens are `map_tokens` instead of the log's.
    map_tokens: optional i32[..., T, M].
    lanes: optional f32[..., L, P, 2] a vector map in the scene frame; lanes_valid: bool[..., L, P];
      use_lanes: bool[...] whether the map slots taken from the given data are these lanes encoded around each
      frame's ego (needs a map encoder in the rollout).
    """

    from_log: jax.Array
    hidden: jax.Array
    max_agents: jax.Array
    agent_given: jax.Array | None = None
    xy: jax.Array | None = None
    heading: jax.Array | None = None
    valid: jax.Array | None = None
    map_given: jax.Array | None = None
    map_tokens: jax.Array | None = None
    lanes: jax.Array | None = None
    lanes_valid: jax.Array | None = None
    use_lanes: jax.Array | None = None

    @property
    def num_frames(self) -> int:
        return self.from_log.shape[-2]

    @property
    def num_agents(self) -> int:
        return self.hidden.shape[-1]

    @property
    def num_map_tokens(self) -> int:
        return self.from_log.shape[-1] - self.hidden.shape[-1]

    def removed(self) -> jax.Array:
        """bool[..., A] slots invalid in every frame: hidden or beyond the agent cap."""
        xp = np if isinstance(self.hidden, np.ndarray) else jax.numpy
        slots = xp.arange(self.hidden.shape[-1])
        return self.hidden | (slots >= xp.asarray(self.max_agents)[..., None])


def as_prompt(task: Task | Prompt, num_frames: int) -> Prompt:
    """A `Task` as the equivalent `Prompt` (its mask repeated over `num_frames` frames, no cap, nothing given
    beyond the log); a `Prompt` is returned unchanged."""
    if isinstance(task, Prompt):
        return task
    if not isinstance(task, Task):
        raise TypeError(f"expected a Task or a Prompt, got {type(task).__name__}")
    xp = np if isinstance(task.from_log, np.ndarray) else jax.numpy
    fl = task.from_log
    from_log = xp.broadcast_to(fl[..., None, :], fl.shape[:-1] + (num_frames, fl.shape[-1]))
    max_agents = xp.full(task.hidden.shape[:-1], task.hidden.shape[-1], xp.int32)
    return Prompt(from_log=from_log, hidden=task.hidden, max_agents=max_agents)


def prompt_from_task(name: str, num_frames: int, num_map_tokens: int, num_agents: int) -> Prompt:
    """The prompt of a named task (numpy leaves): rolls out exactly as the task does."""
    if name not in TASKS:
        raise PromptError(f"unknown task {name!r}; known tasks: {', '.join(TASK_NAMES)}")
    m, e, a, hide = TASKS[name]
    fl = np.concatenate([np.full(num_map_tokens, m), [e], np.full(num_agents - 1, a)]).astype(bool)
    hidden = np.concatenate([[False], np.full(num_agents - 1, hide)]).astype(bool)
    return as_prompt(Task(from_log=fl, hidden=hidden), num_frames)


def generates(prompt: Prompt, num_history: int) -> dict[str, bool]:
    """Whether a single prompt generates the ego, any agent, any map token in some future frame (for scoring
    and pictures)."""
    fl = np.asarray(prompt.from_log)[num_history:]
    m = prompt.num_map_tokens
    keep = ~np.asarray(prompt.removed())
    return {"ego": bool((~fl[:, m]).any() and keep[0]), "agent": bool((~fl[:, m + 1:] & keep[1:]).any()),
            "map": bool((~fl[:, :m]).any())}


# ------------------------------------------------------------------------------------------------- builders


def _heading_of_path(xy: np.ndarray) -> np.ndarray:
    """Headings f32[F] along a path f32[F, 2] (each point towards the next; the last repeats; a standing path
    keeps the previous heading, 0 if it never moves)."""
    d = np.diff(xy, axis=0)
    h = np.arctan2(d[:, 1], d[:, 0]) if len(d) else np.zeros(0)
    moving = np.linalg.norm(d, axis=-1) > 1e-3 if len(d) else np.zeros(0, bool)
    out = np.zeros(len(xy))
    last = 0.0
    for i in range(len(d)):
        if moving[i]:
            last = h[i]
        out[i] = last
    if len(xy):
        out[-1] = out[-2] if len(xy) > 1 else 0.0
    # fill the leading standing points with the first moving heading
    if moving.any():
        out[: int(np.argmax(moving))] = h[int(np.argmax(moving))]
    return out.astype(np.float32)


def resample_lane(points: np.ndarray, spacing: float = LANE_SPACING_M) -> np.ndarray:
    """A polyline f32[P, 2] resampled along its arc length with at most `spacing` metres between points (the
    rasterizer draws segments up to the tokenizer's max_segment_length without gaps)."""
    seg = np.linalg.norm(np.diff(points, axis=0), axis=-1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    n = max(2, int(math.ceil(s[-1] / spacing)) + 1)
    q = np.linspace(0.0, s[-1], n)
    return np.stack([np.interp(q, s, points[:, 0]), np.interp(q, s, points[:, 1])], -1).astype(np.float32)


def lanes_array(lanes: Sequence[Any], *, pose: Sequence[float] | None = None, spacing: float = LANE_SPACING_M,
                where: str = "lanes") -> tuple[np.ndarray, np.ndarray]:
    """A lane list (each an array-like [P_i, 2] of points, P_i >= 2, finite) -> (f32[L, P, 2], bool[L, P]) in
    the scene frame, resampled to `spacing`. With `pose` (x, y, heading of the scene frame in the lanes' world
    frame) the points are moved from that world frame into the scene frame."""
    if len(lanes) == 0:
        raise PromptError(f"{where}: no lanes given")
    out = []
    for i, lane in enumerate(lanes):
        try:
            p = np.asarray(lane, np.float64)
        except (TypeError, ValueError):
            raise PromptError(f"{where}[{i}]: not a list of [x, y] points") from None
        if p.ndim != 2 or p.shape[-1] != 2:
            raise PromptError(f"{where}[{i}]: expected points [[x, y], ...], got shape {p.shape}")
        if len(p) < 2:
            raise PromptError(f"{where}[{i}]: a lane needs at least 2 points, got {len(p)}")
        if not np.isfinite(p).all():
            raise PromptError(f"{where}[{i}]: has NaN or infinite coordinates")
        if pose is not None:
            x0, y0, h0 = (float(v) for v in pose)
            c, s = math.cos(h0), math.sin(h0)
            d = p - np.array([x0, y0])
            p = np.stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]], -1)
        if np.linalg.norm(np.diff(p, axis=0), axis=-1).sum() <= 0:
            raise PromptError(f"{where}[{i}]: all points coincide (zero length)")
        out.append(resample_lane(p, spacing))
    num_p = max(len(p) for p in out)
    pts = np.zeros((len(out), num_p, 2), np.float32)
    ok = np.zeros((len(out), num_p), bool)
    for i, p in enumerate(out):
        pts[i, : len(p)] = p
        ok[i, : len(p)] = True
    return pts, ok


def _frames(frames, num_frames: int, where: str) -> np.ndarray:
    f = np.asarray(frames)
    if f.ndim != 1 or f.size == 0 or f.dtype.kind not in "iu":
        raise PromptError(f"{where}: expected a non-empty list of frame indices, got {frames!r}")
    if (f < 0).any() or (f >= num_frames).any():
        raise PromptError(f"{where}: frames {f.tolist()} out of range [0, {num_frames})")
    if len(np.unique(f)) != len(f):
        raise PromptError(f"{where}: repeated frames {f.tolist()}")
    return f.astype(np.int64)


def _slot(slot, num_agents: int, where: str) -> int:
    if isinstance(slot, bool) or not isinstance(slot, (int, np.integer)):
        raise PromptError(f"{where}: agent slot must be an integer, got {slot!r}")
    if not 0 <= int(slot) < num_agents:
        raise PromptError(f"{where}: unknown agent slot {slot} (the model has slots 0..{num_agents - 1}; 0 is "
                          "the ego)")
    return int(slot)


def _braking_path(scene: Scene, num_history: int, j: int, frames: np.ndarray, decel, period: float | None,
                  where: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Slot j's logged path from the current frame on, driven at a constant deceleration from its current speed:
    (xy f32[F, 2], heading f32[F], valid bool[F]) at `frames` (future frames)."""
    if period is None or period <= 0:
        raise PromptError(f"{where}.decelerate: needs the model's frame period (frame_period_s)")
    try:
        a = float(decel)
    except (TypeError, ValueError):
        raise PromptError(f"{where}.decelerate: expected a deceleration in m/s^2, got {decel!r}") from None
    if not a > 0 or not math.isfinite(a):
        raise PromptError(f"{where}.decelerate: expected a positive deceleration in m/s^2, got {decel!r}")
    if (frames < num_history).any():
        raise PromptError(f"{where}.frames: a braking path is given over future frames (>= {num_history})")
    lxy, lhd, lv = (np.asarray(scene.xy)[:, j].astype(np.float64), np.asarray(scene.heading)[:, j],
                    np.asarray(scene.valid)[:, j])
    c = num_history - 1
    if c < 1 or not (lv[c] and lv[c - 1]):
        return lxy[frames].astype(np.float32), lhd[frames], lv[frames]
    v0 = float(np.linalg.norm(lxy[c] - lxy[c - 1])) / period
    # the path: logged points from the current frame while valid, then straight on along the last heading
    run = [c]
    while run[-1] + 1 < len(lv) and lv[run[-1] + 1]:
        run.append(run[-1] + 1)
    pts = lxy[run]
    last_dir = np.array([math.cos(lhd[run[-1]]), math.sin(lhd[run[-1]])])
    pts = np.concatenate([pts, pts[-1:] + 1000.0 * last_dir[None]], 0)
    seg = np.linalg.norm(np.diff(pts, axis=0), axis=-1)
    cum = np.concatenate([[0.0], np.cumsum(seg)])
    tau = (frames - c) * period
    s_stop = v0 * v0 / (2 * a)
    s = np.where(tau < v0 / a, v0 * tau - 0.5 * a * tau ** 2, s_stop)
    out = np.stack([np.interp(s, cum, pts[:, 0]), np.interp(s, cum, pts[:, 1])], -1)
    i = np.clip(np.searchsorted(cum, s, side="right") - 1, 0, len(seg) - 1)
    d = pts[i + 1] - pts[i]
    return out.astype(np.float32), np.arctan2(d[:, 1], d[:, 0]).astype(np.float32), np.ones(len(frames), bool)


def make_prompt(scene: Scene, num_history: int, *, base: str = "traffic_simulation",
                paths: Mapping[int, Mapping[str, Any]] | None = None, log_until: int | None = None,
                initial_slots: Sequence[int] | None = None, max_agents: int | None = None,
                hidden: Sequence[int] = (), lanes: Sequence[Any] | None = None,
                lanes_pose: Sequence[float] | None = None, map_tokens: Any | None = None,
                map_frames: Sequence[int] | None = None, frame_period_s: float | None = None) -> Prompt:
    """A prompt for one scene in the model's view (`Model.prepare`: T frames, A slots, M map tokens).

    Args:
      scene: one unbatched Scene [T, A, ...]; its log is the given data unless overridden.
      num_history: H (frames [0, H) are the history).
      base: a task name: which slots come from the log at future frames before the choices below.
      paths: {slot: {"frames": [t, ...], "xy": [[x, y], ...], "heading": [...] (optional: along the path),
        "valid": [...] (optional, default all True)}} given agent states (in-painting; frames < H replace the
        history). {"frames": [...], "from": "log"} takes the log's states at those frames instead, and
        {"frames": [future...], "from": "log", "decelerate": a} the logged path driven from the current speed
        with a constant deceleration of a m/s^2 to a stop (needs `frame_period_s`; a slot not logged at the
        last two history frames keeps its log).
      log_until: k: every agent slot (ego included) comes from the log at frames < k, generated after.
      initial_slots: given initial trajectories for a subset of slots: only these slots are present in the
        history (the others are absent there and generated afterwards, if the model brings them in).
      max_agents: agent cap (slots >= max_agents invalid in every frame).
      hidden: slots hidden in every frame.
      lanes: a vector map, a list of polylines [[x, y], ...] in the scene frame (or a world frame with
        `lanes_pose`: the scene frame's pose x, y, heading in it). The map slots are then taken from the given
        data at every frame of `map_frames` (default all; the history always) and are these lanes encoded around
        each frame's ego; the other future frames' maps are generated.
      map_tokens: given map tokens i32[M] (every frame of `map_frames`) or i32[T, M]; map_frames: the frames
        (default all). The map slots of those frames come from the given data.
    """
    t_total, a = scene.xy.shape[-3], scene.xy.shape[-2]
    m = scene.map_tokens.shape[-1]
    if scene.xy.ndim != 3:
        raise PromptError(f"make_prompt takes one scene [T, A, ...], got xy of shape {scene.xy.shape}")
    if not 0 < num_history < t_total:
        raise PromptError(f"num_history {num_history} out of range (1..{t_total - 1})")
    p = prompt_from_task(base, t_total, m, a)
    from_log = np.array(p.from_log)
    hide = np.array(p.hidden)
    xy = np.array(scene.xy, np.float32)
    heading = np.array(scene.heading, np.float32)
    valid = np.array(scene.valid, bool)
    agent_given = np.zeros((t_total, a), bool)
    for s in hidden:
        hide[_slot(s, a, "hidden")] = True
    cap = a
    if max_agents is not None:
        if isinstance(max_agents, bool) or not isinstance(max_agents, (int, np.integer)) or not 1 <= max_agents <= a:
            raise PromptError(f"max_agents must be an integer in 1..{a} (slot 0 is the ego), got {max_agents!r}")
        cap = int(max_agents)
    if log_until is not None:
        if isinstance(log_until, bool) or not isinstance(log_until, (int, np.integer)) or \
                not num_history <= log_until <= t_total:
            raise PromptError(f"log_until must be a frame in {num_history}..{t_total} (history {num_history}, "
                              f"{t_total} frames), got {log_until!r}")
        from_log[:log_until, m:] = True
    if initial_slots is not None:
        keep = np.zeros(a, bool)
        for s in initial_slots:
            keep[_slot(s, a, "initial_slots")] = True
        agent_given[:num_history, ~keep] = True
        valid[:num_history, ~keep] = False
    for slot, spec in (paths or {}).items():
        where = f"paths[{slot}]"
        j = _slot(slot, a, where)
        if not isinstance(spec, Mapping) or "frames" not in spec:
            raise PromptError(f"{where}: expected {{'frames': [...], 'xy': [[x, y], ...]}} or "
                              "{'frames': [...], 'from': 'log'}")
        fr = _frames(spec["frames"], t_total, f"{where}.frames")
        from_log[fr, m + j] = True
        if spec.get("from") == "log" and "decelerate" in spec:
            bxy, bhd, bv = _braking_path(scene, num_history, j, fr, spec["decelerate"], frame_period_s, where)
            xy[fr, j], heading[fr, j], valid[fr, j] = bxy, bhd, bv
            agent_given[fr, j] = True
            continue
        if spec.get("from") == "log":
            continue
        if "from" in spec:
            raise PromptError(f"{where}.from: only 'log' is known, got {spec['from']!r}")
        if "xy" not in spec:
            raise PromptError(f"{where}: no 'xy' (or 'from': 'log') given")
        pxy = np.asarray(spec["xy"], np.float64)
        if pxy.shape != (len(fr), 2):
            raise PromptError(f"{where}.xy: expected {len(fr)} points [x, y] (one per frame), got shape {pxy.shape}")
        if not np.isfinite(pxy).all():
            raise PromptError(f"{where}.xy: has NaN or infinite coordinates")
        if "heading" in spec:
            ph = np.asarray(spec["heading"], np.float64)
            if ph.shape != (len(fr),) or not np.isfinite(ph).all():
                raise PromptError(f"{where}.heading: expected {len(fr)} finite angles, got {spec['heading']!r}")
        else:
            order = np.argsort(fr)
            ph = np.empty(len(fr))
            ph[order] = _heading_of_path(pxy[order])
        pv = np.ones(len(fr), bool) if "valid" not in spec else np.asarray(spec["valid"], bool)
        if pv.shape != (len(fr),):
            raise PromptError(f"{where}.valid: expected {len(fr)} booleans")
        xy[fr, j] = pxy
        heading[fr, j] = (ph + np.pi) % (2 * np.pi) - np.pi
        valid[fr, j] = pv
        agent_given[fr, j] = True
    fields: dict[str, Any] = {}
    if agent_given.any():
        fields.update(agent_given=agent_given, xy=xy, heading=heading, valid=valid)
    if map_tokens is not None:
        tok = np.asarray(map_tokens)
        fr = (np.arange(t_total) if map_frames is None else _frames(map_frames, t_total, "map_frames"))
        if tok.dtype.kind not in "iu" or tok.shape not in ((m,), (t_total, m)):
            raise PromptError(f"map_tokens: expected integers of shape [{m}] or [{t_total}, {m}], got {tok.shape}")
        full = np.broadcast_to(tok, (t_total, m)).astype(np.int32).copy()
        mg = np.zeros(t_total, bool)
        mg[fr] = True
        from_log[fr, :m] = True
        fields.update(map_given=mg, map_tokens=full)
    if lanes is not None:
        pts, ok = lanes_array(lanes, pose=lanes_pose)
        fr = np.arange(t_total) if map_frames is None else _frames(map_frames, t_total, "map_frames")
        from_log[fr, :m] = True  # history frames always carry the lanes (their rows are not read)
        fields.update(lanes=pts, lanes_valid=ok, use_lanes=np.asarray(True))
    return Prompt(from_log=from_log, hidden=hide, max_agents=np.asarray(cap, np.int32), **fields)


# ----------------------------------------------------------------------------------------------- batching

_OPTIONAL = ("agent_given", "xy", "heading", "valid", "map_given", "map_tokens", "lanes", "lanes_valid",
             "use_lanes")


def stack_prompts(prompts: Sequence[Prompt], scene: Scene | None = None) -> Prompt:
    """Single prompts stacked on a new leading dim, with one pytree structure: an optional field that one
    prompt has is filled in the others with what gives no change (nothing given; lanes padded to the largest
    L and P). Agent-state fields need `scene` (the unbatched model view their shapes come from) only when some
    prompts lack them."""
    if not prompts:
        raise PromptError("no prompts to stack")
    ps = [jax.tree.map(np.asarray, p) for p in prompts]
    t_total, a = ps[0].from_log.shape[0], ps[0].hidden.shape[0]
    m = ps[0].from_log.shape[1] - a
    for i, p in enumerate(ps):
        if p.from_log.shape != (t_total, m + a):
            raise PromptError(f"prompt {i}: from_log shape {p.from_log.shape}, expected {(t_total, m + a)}")
    has = {f: any(getattr(p, f) is not None for p in ps) for f in _OPTIONAL}
    num_l = max((p.lanes.shape[0] for p in ps if p.lanes is not None), default=0)
    num_p = max((p.lanes.shape[1] for p in ps if p.lanes is not None), default=0)
    out = []
    for p in ps:
        upd: dict[str, Any] = {}
        if has["agent_given"] and p.agent_given is None:
            upd.update(agent_given=np.zeros((t_total, a), bool), xy=np.zeros((t_total, a, 2), np.float32),
                       heading=np.zeros((t_total, a), np.float32), valid=np.zeros((t_total, a), bool))
        if has["map_given"] and p.map_given is None:
            upd.update(map_given=np.zeros(t_total, bool), map_tokens=np.zeros((t_total, m), np.int32))
        if has["lanes"]:
            if p.lanes is None:
                upd.update(lanes=np.zeros((num_l, num_p, 2), np.float32), lanes_valid=np.zeros((num_l, num_p), bool),
                           use_lanes=np.asarray(False))
            else:
                ln = np.zeros((num_l, num_p, 2), np.float32)
                lv = np.zeros((num_l, num_p), bool)
                ln[: p.lanes.shape[0], : p.lanes.shape[1]] = p.lanes
                lv[: p.lanes.shape[0], : p.lanes.shape[1]] = p.lanes_valid
                upd.update(lanes=ln, lanes_valid=lv)
        out.append(p.replace(**upd))
    return jax.tree.map(lambda *xs: np.stack(xs), *out)


# ------------------------------------------------------------------------------------------------ JSON file

_KEYS = {"base", "log_until", "initial_slots", "max_agents", "hidden", "agents", "lanes", "comment"}
_AGENT_KEYS = {"slot", "frames", "xy", "heading", "valid", "from", "decelerate", "comment"}
_LANE_KEYS = {"frame", "pose", "polylines", "comment"}


def prompt_from_json(obj: Mapping[str, Any], scene: Scene, num_history: int, *, has_tokenizer: bool = True,
                     where: str = "prompt", frame_period_s: float | None = None) -> Prompt:
    """The prompt of a JSON prompt file's content for one scene in the model's view. Every problem raises
    `PromptError` naming the JSON path. Examples: examples/prompt_*.json. Format (every key optional):

        {"base": "traffic_simulation",                      # a task name: the slots from the log at first
         "agents": [{"slot": 3, "frames": "future" | "all" | [t, ...],
                     "xy": [[x, y], ...], "heading": [...], "valid": [...]},        # given states
                    {"slot": 4, "frames": ..., "from": "log", "decelerate": 3.0}],  # the log (braking on it)
         "log_until": 6, "initial_slots": [0, 1, 2], "max_agents": 5, "hidden": [7],
         "lanes": {"frame": "scene" | "world", "pose": [x, y, heading], "polylines": [[[x, y], ...], ...]}
                  | [[[x, y], ...], ...] | "log",
         "comment": "free text"}

    Frames are the model's (0 .. T-1, the first num_history the history); coordinates are metres in the scene
    frame (the ego frame of the current frame) unless lanes say "world" with the scene frame's pose."""
    if not isinstance(obj, Mapping):
        raise PromptError(f"{where}: expected a JSON object at the top level")
    unknown = set(obj) - _KEYS
    if unknown:
        raise PromptError(f"{where}: unknown keys {sorted(unknown)} (known: {sorted(_KEYS)})")
    t_total, a = scene.xy.shape[-3], scene.xy.shape[-2]
    base = obj.get("base", "traffic_simulation")
    if base not in TASKS:
        raise PromptError(f"{where}.base: unknown task {base!r}; known tasks: {', '.join(TASK_NAMES)}")
    paths: dict[int, dict[str, Any]] = {}
    json_path: dict[str, str] = {}  # make_prompt's name of a path -> its JSON path, for the messages
    agents = obj.get("agents", [])
    if not isinstance(agents, list):
        raise PromptError(f"{where}.agents: expected a list of agent objects")
    for i, ag in enumerate(agents):
        w = f"{where}.agents[{i}]"
        if not isinstance(ag, Mapping):
            raise PromptError(f"{w}: expected an object")
        bad = set(ag) - _AGENT_KEYS
        if bad:
            raise PromptError(f"{w}: unknown keys {sorted(bad)} (known: {sorted(_AGENT_KEYS)})")
        if "slot" not in ag:
            raise PromptError(f"{w}: no 'slot'")
        j = _slot(ag["slot"], a, f"{w}.slot")
        if j in paths:
            raise PromptError(f"{w}.slot: slot {j} given twice")
        if "frames" not in ag:  # no silent default: a path over the wrong frames looks like a model's failure
            raise PromptError(f"{w}: no 'frames' (a list of frame indices, \"future\" or \"all\")")
        frames = ag["frames"]
        if frames == "future":
            frames = list(range(num_history, t_total))
        elif frames == "all":
            frames = list(range(t_total))
        _frames(frames, t_total, f"{w}.frames")
        paths[j] = {k: v for k, v in ag.items() if k not in ("slot", "comment")} | {"frames": frames}
        json_path[f"paths[{j}]"] = w
    lanes = pose = None
    if "lanes" in obj:
        ln = obj["lanes"]
        w = f"{where}.lanes"
        if not has_tokenizer:
            raise PromptError(f"{w}: a vector-map prompt needs the model's map tokenizer to encode the lanes, and "
                              "the model has none")
        if ln == "log":  # the scene's own lanes as a vector map (its map tokens not used)
            if scene.polylines is None:
                raise PromptError(f"{w}: 'log' needs the scene's lane polylines, and it has none")
            pl, pv = np.asarray(scene.polylines), np.asarray(scene.polyline_valid, bool)
            ln = {"polylines": [pl[i][pv[i]].tolist() for i in range(len(pl)) if pv[i].sum() >= 2]}
        if isinstance(ln, list):
            ln = {"polylines": ln}
        if not isinstance(ln, Mapping) or "polylines" not in ln:
            raise PromptError(f"{w}: expected a list of polylines or {{'polylines': [...], 'frame': ...}}")
        bad = set(ln) - _LANE_KEYS
        if bad:
            raise PromptError(f"{w}: unknown keys {sorted(bad)} (known: {sorted(_LANE_KEYS)})")
        frame = ln.get("frame", "scene")
        if frame not in ("scene", "world"):
            raise PromptError(f"{w}.frame: 'scene' or 'world', got {frame!r}")
        if frame == "world":
            pose = ln.get("pose")
            if not (isinstance(pose, list) and len(pose) == 3 and all(isinstance(v, (int, float)) for v in pose)):
                raise PromptError(f"{w}.pose: a world-frame lane list needs the scene frame's pose [x, y, heading]")
        lanes = ln["polylines"]
        if not isinstance(lanes, list):
            raise PromptError(f"{w}.polylines: expected a list of polylines")
        lanes_array(lanes, pose=pose, where=f"{w}.polylines")  # validate with the JSON path
    try:
        return make_prompt(scene, num_history, base=base, paths=paths, log_until=obj.get("log_until"),
                           initial_slots=obj.get("initial_slots"), max_agents=obj.get("max_agents"),
                           hidden=obj.get("hidden", []), lanes=lanes, lanes_pose=pose,
                           frame_period_s=frame_period_s)
    except PromptError as e:
        msg = str(e)
        named = next((k for k in json_path if msg.startswith(k + ".") or msg.startswith(k + ":")), None)
        raise PromptError(json_path[named] + msg[len(named):] if named else f"{where}: {msg}") from None
