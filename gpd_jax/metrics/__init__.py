"""Metrics of GPD-1: agent ADE / FDE / collision and map F1 / lateral / Chamfer, each in the official code's
("paper") and a corrected variant, plus the Hungarian line matching shared with the map tokenizer; and the
distributional realism of sampled rollouts in the form of the Waymo sim-agents challenge (`realism`).

Every metric is computed as sums and counts over a batch (`*_metric_sums`, jit/vmap-able, leading batch dims free)
that add up exactly across batches (`accumulate`), then turned into numbers by a reducer (`reduce_*_metrics`).
"""

from gpd_jax.metrics.agents import (DEFAULT_HORIZONS, MOTION_CLASSES, PAPER_BOX, STATIONARY_MPS, TRACK_COMPONENTS,
                                    VARIANTS, accumulate, agent_metric_sums, agent_metrics, box_corners,
                                    box_overlap_pairwise, horizon_label, reduce_agent_metrics)
from gpd_jax.metrics.map import (lateral_distances, map_metric_sums, map_metrics, point_to_line_distance,
                                 reduce_map_metrics, set_chamfer)
from gpd_jax.metrics.matching import gather_matched, hungarian, line_match_cost, match_lines
from gpd_jax.metrics.realism import (realism_weights, reduce_realism, scenario_realism, upsample_frames)

__all__ = [
    "DEFAULT_HORIZONS", "MOTION_CLASSES", "PAPER_BOX", "STATIONARY_MPS", "TRACK_COMPONENTS", "VARIANTS",
    "accumulate",
    "agent_metric_sums", "agent_metrics", "reduce_agent_metrics", "horizon_label",
    "box_corners", "box_overlap_pairwise",
    "map_metric_sums", "map_metrics", "reduce_map_metrics", "lateral_distances", "point_to_line_distance",
    "set_chamfer",
    "gather_matched", "hungarian", "line_match_cost", "match_lines",
    "scenario_realism", "reduce_realism", "realism_weights", "upsample_frames",
]
