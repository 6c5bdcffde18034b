"""Metrics of GPD-1 (paper-faithful and corrected variants) and the line matching they share."""

from gpd_jax.metrics.matching import gather_matched, hungarian, line_match_cost, match_lines

__all__ = ["gather_matched", "hungarian", "line_match_cost", "match_lines"]
