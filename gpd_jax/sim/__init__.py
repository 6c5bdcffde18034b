"""Closed-loop simulation over the KV-cached GPD: your planner in the loop, GPD / log-replay / IDM agents, and
nuPlan's planning scores (OLS, CLS with its multipliers and weighted terms) at the stored rate.

    import gpd_jax, jax
    from gpd_jax import sim
    model = gpd_jax.load_model()
    scenes = sim.make_sim_scenes(model, gpd_jax.load_scenes(store, indices=range(8)))
    out = sim.run(model, scenes, sim.make_policy("cv", model), jax.random.key(0), agents="gpd")
    scores = sim.score_runs(model.spec, scenes, out)          # per-scenario CLS and its terms
"""

from gpd_jax.sim.agents import IDMParams, IDMState, Paths
from gpd_jax.sim.core import (AGENT_MODELS, Observation, Policy, RunCarry, SimError, SimResult, SimScene, SimState,
                              as_policy, make_sim_scenes, observe, reset, run, run_host, step)
from gpd_jax.sim.dynamics import BicycleLimits, bicycle_path
from gpd_jax.sim.policies import (HEAD_PLANNERS, PLANNERS, constant_velocity_policy, expert_policy, gpd_head_policy, gpd_policy,
                                  idm_policy, make_policy)

__all__ = [
    "AGENT_MODELS", "HEAD_PLANNERS", "PLANNERS", "BicycleLimits", "IDMParams", "IDMState", "Observation", "Paths", "Policy",
    "RunCarry", "SimError", "SimResult", "SimScene", "SimState", "as_policy", "bicycle_path",
    "constant_velocity_policy", "expert_policy", "gpd_head_policy", "gpd_policy", "idm_policy", "make_policy",
    "make_sim_scenes", "observe", "reset", "run", "run_host", "step",
]
