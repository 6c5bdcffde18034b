"""The scene format shared by every data source, the model, the rollout and the metrics.

A `Scene` is a frozen pytree of fixed-shape arrays with validity masks (never ragged), with any number of
free leading batch dimensions written `...` below. Conventions (see DESIGN.md):

* units are metres and radians; x forward, y left, heading counter-clockwise, wrapped to [-pi, pi);
* agents are expressed in the ego frame of the *current* frame (index `num_history - 1`, 20 in the paper
  configuration): the ego box centre at the current frame is the origin and its heading is zero;
* slot 0 is the ego; slots 1.. are the surrounding vehicles;
* the map of frame t (tokens and vector lanes) is expressed in the ego frame of frame t, which is the
  pose `ego_pose[..., t, :]` in scene coordinates.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import flax.struct
import jax
import jax.numpy as jnp
import numpy as np

# Agent types. Vehicles only in GPD-1; the type is kept to size boxes and to colour pictures.
AGENT_TYPES = ("ego", "car", "van", "truck", "bus", "motorcycle", "other")
TYPE_ID = {name: i for i, name in enumerate(AGENT_TYPES)}


def wrap_angle(a):
    """Wraps angles to [-pi, pi)."""
    return (a + jnp.pi) % (2 * jnp.pi) - jnp.pi


@flax.struct.dataclass(frozen=True)
class Scene:
    """One driving scene (or a batch of them: every field shares the leading dims `...`).

    Attributes:
      xy: f32[..., T, A, 2] agent box centres in the scene frame (ego frame of the current frame).
      heading: f32[..., T, A] agent headings in the scene frame, wrapped to [-pi, pi).
      valid: bool[..., T, A] whether the agent is observed in that frame (padding slots are never valid).
      size: f32[..., A, 2] box (length, width) in metres per agent slot.
      agent_type: i32[..., A] index into `AGENT_TYPES`.
      map_tokens: i32[..., T, M] map VQ token of each 8x8 cell per frame, row-major over the grid
        (row = forward axis x from front to back, column = lateral axis y from left to right).
      map_valid: bool[..., T] whether `map_tokens` of the frame are known (False where no tokenizer ran).
      ego_pose: f32[..., T, 3] (x, y, heading) of the ego in the scene frame; the pose the frame's map is
        expressed in. Equals `(xy[..., 0, :], heading[..., 0])` where the ego is valid.
      lanes: optional f32[..., T, L, P, 2] vector lanes of each frame in that frame's ego frame
        (SLEDGE processing: L=50 nearest lines, P=20 points each).
      lanes_valid: optional bool[..., T, L] which lane slots are present.
      velocity: optional f32[..., T, A, 2] instantaneous velocity (m/s, scene frame) of each agent, a finite
        backward difference at the stored frame rate to its last valid frame (see `with_velocity`); zero where
        the agent is not valid or has no earlier valid frame, and at frame 0.
      polylines: optional f32[..., L, P, 2] the log's lane centrelines in the scene frame (not per frame): what
        a map tokenizer rasterizes around any ego pose (map tokens made on the fly, lanes re-encoded around a
        generated ego, map metrics' ground truth).
      polyline_valid: optional bool[..., L, P] which polyline points exist.
      road: optional `gpd_jax.geometry.RoadGeometry` (same leading dims): drivable-area rings, road edges and
        directed lane centrelines in the scene frame, queried with `gpd_jax.geometry.on_road`,
        `signed_distance_to_edge` and `lane_direction`. Not per frame: `subsample` / `slice_frames` keep it.
        None for stores built before the geometry existed (rebuild with `python -m gpd_jax.data build ...`).
      signals: optional `gpd_jax.geometry.TrafficSignals` (same leading dims): traffic-light states per frame
        (`state i32[..., T, S]`, cut with the frames) at stop points on controlled lanes; None where the store
        has none (sources without signals, stores before format 2).
    """

    xy: jax.Array
    heading: jax.Array
    valid: jax.Array
    size: jax.Array
    agent_type: jax.Array
    map_tokens: jax.Array
    map_valid: jax.Array
    ego_pose: jax.Array
    lanes: jax.Array | None = None
    lanes_valid: jax.Array | None = None
    velocity: jax.Array | None = None
    polylines: jax.Array | None = None
    polyline_valid: jax.Array | None = None
    road: "RoadGeometry | None" = None  # noqa: F821 (gpd_jax.geometry, a sibling layer: not imported here)
    signals: "TrafficSignals | None" = None  # noqa: F821 (gpd_jax.geometry)

    # ---------------------------------------------------------------- shapes
    @property
    def batch_shape(self) -> tuple[int, ...]:
        return tuple(self.xy.shape[:-3])

    @property
    def num_frames(self) -> int:
        return self.xy.shape[-3]

    @property
    def num_agents(self) -> int:
        return self.xy.shape[-2]

    @property
    def num_map_tokens(self) -> int:
        return self.map_tokens.shape[-1]

    def validate(self) -> "Scene":
        """Checks every field's shape against the others and raises one error naming all that are wrong.

        Returns the scene itself so it can be chained: `scene = Scene(...).validate()`.
        """
        validate_fields(_scene_spec(self), {f.name: getattr(self, f.name) for f in dataclasses.fields(self)},
                        where="Scene")
        if self.road is not None:
            self.road.validate(batch_shape=self.batch_shape, where="Scene.road")
        return self

    def slice_frames(self, start: int, stop: int) -> "Scene":
        """Frames [start, stop) of every per-frame field."""
        per_frame = {"xy": -3, "heading": -2, "valid": -2, "map_tokens": -2, "map_valid": -1, "ego_pose": -2,
                     "lanes": -4, "lanes_valid": -2, "velocity": -3}
        updates = {}
        for name, axis in per_frame.items():
            v = getattr(self, name)
            if v is not None:
                updates[name] = jax.lax.slice_in_dim(v, start, stop, axis=v.ndim + axis)
        if self.signals is not None:
            st = self.signals.state
            updates["signals"] = self.signals.replace(state=jax.lax.slice_in_dim(st, start, stop, axis=st.ndim - 2))
        return self.replace(**updates)

    def subsample(self, stride: int = 1, num_frames: int | None = None, num_agents: int | None = None,
                  start: int = 0, velocity_period_s: float | None = None) -> "Scene":
        """Every `stride`-th frame from `start` (at most `num_frames` of them) and the first `num_agents` slots.

        Works on numpy and JAX leaves alike (plain strided slicing). Slot 0 (the ego) is always kept; the
        stored slots are ordered by distance to the ego, so a prefix keeps the nearest agents. With
        `velocity_period_s` (seconds between this scene's frames), `velocity` is first computed at this scene's
        full frame rate (`with_velocity`), so a subsampled frame still carries its instantaneous velocity.
        """
        if velocity_period_s is not None:
            return self.with_velocity(velocity_period_s).subsample(stride, num_frames, num_agents, start)
        stop = self.num_frames if num_frames is None else start + stride * (num_frames - 1) + 1
        if stop > self.num_frames:
            raise ValueError(f"{num_frames} frames at stride {stride} from frame {start} need {stop} frames; "
                             f"the scene has {self.num_frames}")
        a = self.num_agents if num_agents is None else num_agents
        if not 1 <= a <= self.num_agents:
            raise ValueError(f"num_agents {a} not in [1, {self.num_agents}]")
        fr = slice(start, stop, stride)
        e = (Ellipsis,)
        upd = {
            "xy": self.xy[e + (fr, slice(0, a), slice(None))], "heading": self.heading[e + (fr, slice(0, a))],
            "valid": self.valid[e + (fr, slice(0, a))], "size": self.size[e + (slice(0, a), slice(None))],
            "agent_type": self.agent_type[e + (slice(0, a),)], "map_tokens": self.map_tokens[e + (fr, slice(None))],
            "map_valid": self.map_valid[e + (fr,)], "ego_pose": self.ego_pose[e + (fr, slice(None))],
        }
        if self.lanes is not None:
            upd["lanes"] = self.lanes[e + (fr,) + (slice(None),) * 3]
            upd["lanes_valid"] = self.lanes_valid[e + (fr, slice(None))]
        if self.velocity is not None:
            upd["velocity"] = self.velocity[e + (fr, slice(0, a), slice(None))]
        if self.signals is not None:
            upd["signals"] = self.signals.replace(state=self.signals.state[e + (fr, slice(None))])
        return self.replace(**upd)

    def with_velocity(self, period_s: float) -> "Scene":
        """The scene with `velocity` set from its own frames, `period_s` seconds apart (numpy or JAX leaves).

        Frame t's velocity is the backward difference to the agent's last valid frame t' < t, (xy[t] - xy[t'])
        / ((t - t') period_s), where the agent is valid at t (`backward_difference`): a track missing for a few
        frames, as sensor logs have, keeps its speed, by the same rule `constant_velocity` extrapolates with.
        Zero where the agent has no earlier valid frame (first seen at t), is not valid at t, and at frame 0;
        never a forward difference (that would show a model the future).
        """
        if period_s <= 0:
            raise ValueError(f"velocity period must be positive, got {period_s}")
        step, frames, known = backward_difference(self.xy, self.valid)
        vel = step / (frames * period_s)[..., None]
        xp = jnp if isinstance(vel, jax.Array) else np
        return self.replace(velocity=xp.where(known[..., None], vel, 0.0).astype(self.xy.dtype))


def backward_difference(xy, valid):
    """Each agent's displacement from its last valid frame before t to t (numpy or JAX leaves).

    Args:
      xy: f32[..., T, A, 2]; valid: bool[..., T, A].

    Returns:
      (step f32[..., T, A, 2] = xy[t] - xy[t'], frames f32[..., T, A] = t - t' (1 where unknown),
      known bool[..., T, A]: valid at t with an earlier valid frame t'). `step` is zero where not known.
    """
    xp = jnp if isinstance(xy, jax.Array) or isinstance(valid, jax.Array) else np
    t = valid.shape[-2]
    index = xp.arange(t).reshape((t, 1))
    marked = xp.where(valid, index, -1)
    upto = (jax.lax.cummax(marked, axis=marked.ndim - 2) if xp is jnp
            else np.maximum.accumulate(marked, axis=-2))            # last valid frame <= t
    prev = xp.concatenate([xp.full_like(upto[..., :1, :], -1), upto[..., :-1, :]], -2)  # last valid frame < t
    known = valid & (prev >= 0)
    earlier = xp.take_along_axis(xy, xp.maximum(prev, 0)[..., None], axis=-3)
    step = xp.where(known[..., None], xy - earlier, 0.0)
    frames = xp.where(known, index - prev, 1).astype(xy.dtype)
    return step, frames, known


def _scene_spec(scene: Scene) -> dict[str, tuple[tuple[Any, ...], Any]]:
    """Expected (shape suffix, dtype kind) of each field, with symbolic dims resolved from `xy`/`map_tokens`."""
    spec = {
        "xy": (("T", "A", 2), "f"),
        "heading": (("T", "A"), "f"),
        "valid": (("T", "A"), "b"),
        "size": (("A", 2), "f"),
        "agent_type": (("A",), "i"),
        "map_tokens": (("T", "M"), "i"),
        "map_valid": (("T",), "b"),
        "ego_pose": (("T", 3), "f"),
    }
    if scene.lanes is not None or scene.lanes_valid is not None:
        spec["lanes"] = (("T", "L", "P", 2), "f")
        spec["lanes_valid"] = (("T", "L"), "b")
    if scene.velocity is not None:
        spec["velocity"] = (("T", "A", 2), "f")
    if scene.polylines is not None or scene.polyline_valid is not None:
        spec["polylines"] = (("Lp", "Pp", 2), "f")
        spec["polyline_valid"] = (("Lp", "Pp"), "b")
    return spec


def validate_fields(spec: dict[str, tuple[tuple[Any, ...], str]], values: dict[str, Any], where: str) -> None:
    """Checks named arrays against shape suffixes with symbolic dims and a common batch prefix.

    `spec[name] = (suffix, kind)`: `suffix` mixes ints and symbol strings; every use of a symbol must agree;
    `kind` is a numpy dtype kind ('f' float, 'i' integer (signed or unsigned), 'b' bool). All arrays must
    share the same leading batch shape. Raises ValueError listing every problem, naming the field.
    """
    problems: list[str] = []
    dims: dict[str, tuple[int, str]] = {}
    batch: tuple[tuple[int, ...], str] | None = None
    for name, (suffix, kind) in spec.items():
        v = values.get(name)
        if v is None:
            problems.append(f"{name}: missing (expected shape [..., {', '.join(map(str, suffix))}])")
            continue
        shape = tuple(np.shape(v))
        dt = np.dtype(v.dtype) if hasattr(v, "dtype") else np.asarray(v).dtype
        ok_kind = dt.kind == kind or (kind == "i" and dt.kind == "u")
        if not ok_kind:
            problems.append(f"{name}: dtype {dt} but expected kind {_KIND_NAMES[kind]}")
        if len(shape) < len(suffix):
            problems.append(f"{name}: shape {shape} has fewer than {len(suffix)} dims "
                            f"(expected [..., {', '.join(map(str, suffix))}])")
            continue
        tail = shape[len(shape) - len(suffix):]
        lead = shape[: len(shape) - len(suffix)]
        if batch is None:
            batch = (lead, name)
        elif lead != batch[0]:
            problems.append(f"{name}: batch dims {lead} differ from {batch[1]}'s {batch[0]}")
        for want, got in zip(suffix, tail):
            if isinstance(want, int):
                if want != got:
                    problems.append(f"{name}: shape {shape}, expected [..., {', '.join(map(str, suffix))}] "
                                    f"(a dim is {got}, not {want})")
                    break
            elif want in dims and dims[want][0] != got:
                problems.append(f"{name}: dim {want}={got} in shape {shape} but {dims[want][1]} has "
                                f"{want}={dims[want][0]}")
                break
            else:
                dims.setdefault(want, (got, name))
    if problems:
        raise ValueError(f"invalid {where}:\n  " + "\n  ".join(problems))


_KIND_NAMES = {"f": "float", "i": "integer", "b": "bool"}


def ego_pose_from_agents(xy: jax.Array, heading: jax.Array) -> jax.Array:
    """f32[..., T, 3] ego pose (slot 0) per frame from `xy: f32[..., T, A, 2]` and `heading: f32[..., T, A]`."""
    return jnp.concatenate([xy[..., 0, :], heading[..., 0:1]], axis=-1)


def empty_scene(num_frames: int, num_agents: int, num_map_tokens: int, batch_shape: tuple[int, ...] = (),
                num_lanes: int | None = None, num_lane_points: int = 20) -> Scene:
    """An all-invalid scene of the given shape (useful as a template and in tests)."""
    b = tuple(batch_shape)
    T, A, M = num_frames, num_agents, num_map_tokens
    lanes = lanes_valid = None
    if num_lanes is not None:
        lanes = jnp.zeros(b + (T, num_lanes, num_lane_points, 2), jnp.float32)
        lanes_valid = jnp.zeros(b + (T, num_lanes), bool)
    return Scene(
        xy=jnp.zeros(b + (T, A, 2), jnp.float32),
        heading=jnp.zeros(b + (T, A), jnp.float32),
        valid=jnp.zeros(b + (T, A), bool),
        size=jnp.broadcast_to(jnp.array([4.5, 1.9], jnp.float32), b + (A, 2)),
        agent_type=jnp.full(b + (A,), TYPE_ID["car"], jnp.int32).at[..., 0].set(TYPE_ID["ego"]),
        map_tokens=jnp.zeros(b + (T, M), jnp.int32),
        map_valid=jnp.zeros(b + (T,), bool),
        ego_pose=jnp.zeros(b + (T, 3), jnp.float32),
        lanes=lanes,
        lanes_valid=lanes_valid,
    )
