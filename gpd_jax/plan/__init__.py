"""`python -m gpd_jax.plan {evaluate,bench}`: planners in the closed loop scored with nuPlan's definitions, and
the simulator's throughput. Thin over `gpd_jax.sim` (see `gpd_jax/plan/__main__.py`)."""
