"""gpd_jax: GPD-1 (Generative Pre-training for Driving) in JAX/Flax."""

from gpd_jax.scene import AGENT_TYPES, TYPE_ID, Scene, empty_scene, wrap_angle

__all__ = ["AGENT_TYPES", "TYPE_ID", "Scene", "empty_scene", "wrap_angle"]
__version__ = "0.1.0"
