"""Closed-loop simulation over the KV-cached GPD: your planner in the loop, GPD / log-replay / IDM agents, and
nuPlan's planning scores (OLS, CLS with its multipliers and weighted terms) at the stored rate.

    import gpd_jax, jax, jax.numpy as jnp
    from gpd_jax import sim
    model = gpd_jax.load_model()
    scenes = gpd_jax.load_scenes(store, indices=range(8))           # stored-rate scenes with road geometry
    sims = sim.make_sim_scenes(model, scenes)                        # SimScene [8, ...]
    out = sim.run(model, sims, sim.make_policy("cv", model), jax.random.key(0), agents="gpd")
    s = sim.score(model, sims, out)         # per-scenario CLS and its terms (+ OLS where the policy plans): f32[8]

    # your own policy (pure functions: `Policy`), scored beside the shipped ones, the table of `python -m
    # gpd_jax.plan evaluate` (OLS, NR-CLS, R-CLS-idm, R-CLS-gpd, subscores)
    mine = sim.Policy(name="brake", select=lambda params, obs, state, key: (jnp.array([-2.0, 0.0]), state))
    results = sim.evaluate_planners(model, scenes, {"expert": "log", "idm": "idm", "brake": mine},
                                    agents=("log", "idm", "gpd"))
    print(sim.planning_table(results))

`world_planner_policy` (``gpd_world``) plans with the world model: candidate plans scored with nuPlan's terms on the
futures the model imagines for each (`gpd_jax.sim.world_planner`).

A plain-Python planner on numpy observations runs through `run_host` (its SimResult scores with `score` alike).

Every run follows the policy's output with a `Tracker` (pure pursuit and a speed law on the bicycle model, at the
stored rate; `gpd_jax.sim.tracker`), replanning every `Tracker.replan_every` model frames; a policy may return a
`Plan` (poses at the next F model frames) to be followed beyond the next frame. `tracker=None` places the ego on
the policy's output instead.
"""

from gpd_jax.sim.agents import IDMParams, IDMState, Paths
from gpd_jax.sim.core import (AGENT_MODELS, Observation, Policy, RunCarry, SimError, SimResult, SimScene, SimState,
                              as_policy, make_sim_scenes, observe, reset, run, run_host, step)
from gpd_jax.sim.dynamics import BicycleLimits, bicycle_path
from gpd_jax.sim.policies import (HEAD_PLANNERS, PLANNERS, constant_velocity_policy, expert_policy, gpd_head_policy, gpd_policy,
                                  idm_policy, make_policy)
from gpd_jax.sim.scoring import evaluate_planners, planning_table, score
from gpd_jax.sim.tracker import Plan, Tracker
from gpd_jax.sim.world_planner import WORLD_PLANNERS, WorldPlannerOptions, make_world_policy, world_planner_policy

__all__ = [
    "AGENT_MODELS", "HEAD_PLANNERS", "PLANNERS", "BicycleLimits", "IDMParams", "IDMState", "Observation", "Paths", "Policy",
    "RunCarry", "SimError", "SimResult", "SimScene", "SimState", "as_policy", "bicycle_path",
    "constant_velocity_policy", "evaluate_planners", "expert_policy", "gpd_head_policy", "gpd_policy", "idm_policy",
    "make_policy", "make_sim_scenes", "observe", "planning_table", "reset", "run", "run_host", "score", "step",
    "Plan", "Tracker", "WORLD_PLANNERS", "WorldPlannerOptions", "make_world_policy", "world_planner_policy",
]
