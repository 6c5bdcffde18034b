"""Tasks as data: which token slots are taken from the log at future frames.

A task is a boolean mask over the N = M + A slots of a frame (map slots first, then ego, then agents) saying
which are copied from the log at future frames, plus a mask of agents hidden in every frame. Because a task is
an array, one compiled rollout runs a batch that mixes tasks.

| key                       | from the log at future frames | generated          | hidden |
|---------------------------|-------------------------------|--------------------|--------|
| scene_generation          | nothing                       | map, ego, agents   |        |
| traffic_simulation        | map                           | ego, agents        |        |
| closed_loop               | map, ego                      | agents             |        |
| motion_planning           | map, agents                   | ego                |        |
| map_prediction            | ego, agents                   | map                |        |
| map_prediction_ego_only   | ego                           | map                | agents |
"""

from __future__ import annotations

from collections.abc import Sequence

import flax.struct
import jax
import numpy as np

# name: (map from log, ego from log, agents from log, agents hidden in every frame)
TASKS: dict[str, tuple[bool, bool, bool, bool]] = {
    "scene_generation": (False, False, False, False),
    "traffic_simulation": (True, False, False, False),
    "closed_loop": (True, True, False, False),
    "motion_planning": (True, False, True, False),
    "map_prediction": (False, True, True, False),
    "map_prediction_ego_only": (False, True, False, True),
}
TASK_NAMES = tuple(TASKS)


@flax.struct.dataclass
class Task:
    """from_log: bool[..., M + A] slots copied from the log at future frames; hidden: bool[..., A] agents
    removed (invalid) in every frame, history included."""

    from_log: jax.Array
    hidden: jax.Array


def make_task(name: str, num_map_tokens: int, num_agents: int) -> Task:
    """The task mask of a named task (see the table in the module docstring)."""
    if name not in TASKS:
        raise KeyError(f"unknown task {name!r}; known tasks: {', '.join(TASK_NAMES)}")
    m, e, a, hide = TASKS[name]
    from_log = np.concatenate([np.full(num_map_tokens, m), [e], np.full(num_agents - 1, a)]).astype(bool)
    hidden = np.concatenate([[False], np.full(num_agents - 1, hide)]).astype(bool)
    return Task(from_log=from_log, hidden=hidden)


def make_tasks(names: Sequence[str], num_map_tokens: int, num_agents: int) -> Task:
    """Stacked tasks with a leading dim of len(names). `names` may be ["all"] for every task."""
    names = resolve_task_names(names)
    tasks = [make_task(n, num_map_tokens, num_agents) for n in names]
    return jax.tree.map(lambda *xs: np.stack(xs), *tasks)


def resolve_task_names(names: Sequence[str] | str) -> tuple[str, ...]:
    if isinstance(names, str):
        names = [n for n in names.split(",") if n]
    if list(names) == ["all"]:
        return TASK_NAMES
    for n in names:
        if n not in TASKS:
            raise KeyError(f"unknown task {n!r}; known tasks: {', '.join(TASK_NAMES)}")
    return tuple(names)


def generated(task: str) -> tuple[str, ...]:
    """What a named task generates (and is scored on): a subset of ("ego", "agent", "map") in that order."""
    map_log, ego_log, agents_log, hidden = TASKS[task]
    out = []
    if not ego_log:
        out.append("ego")
    if not (agents_log or hidden):
        out.append("agent")
    if not map_log:
        out.append("map")
    return tuple(out)


def map_task_names(task_names: Sequence[str]) -> tuple[str, ...]:
    """The tasks among `task_names` that generate the map, in order."""
    return tuple(n for n in task_names if "map" in generated(n))
