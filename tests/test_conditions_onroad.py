"""Off-road share of generated agents from the drivable area (`gpd_jax.evaluation.conditions.lane_offroad`): the
store's geometry, a hand-drawn road's area built from its lanes, the lane-distance figure under its own name, and
stores without geometry."""

import types

import numpy as np
import pytest

from gpd_jax.evaluation import conditions as cond
from gpd_jax.geometry import AREA_KIND_ID, RoadGeometry, on_road
from gpd_jax.prompts import prompt_from_task

T, H, A, M = 5, 2, 4, 8  # frames, history, slots, map tokens
PROMPT = prompt_from_task("traffic_simulation", T, M, A)  # ego and agents generated in the future frames


def straight_lanes():
    """Two parallel lanes along x in [0, 100] m, centrelines at y = 0 and y = 3.5."""
    x = np.linspace(0.0, 100.0, 101)
    lanes = np.stack([np.stack([x, np.zeros_like(x)], -1), np.stack([x, np.full_like(x, 3.5)], -1)])
    return lanes.astype(np.float32), np.ones(lanes.shape[:2], bool)


def rollout(y_per_slot, x=50.0, heading=0.0):
    """Every slot at (x, y) in every frame, all valid."""
    xy = np.zeros((T, A, 2), np.float32)
    xy[..., 0] = x
    xy[..., 1] = np.asarray(y_per_slot, np.float32)
    return types.SimpleNamespace(xy=xy, heading=np.full((T, A), heading, np.float32), valid=np.ones((T, A), bool))


def test_hand_drawn_road_area_covers_its_lanes_at_the_lane_width():
    lanes, ok = straight_lanes()
    road = cond.road_from_lanes(lanes, ok)
    road.validate()
    pts = np.array([[50, 0], [50, 3.5], [50, -1.6], [50, 5.1], [50, -1.9], [50, 5.4], [-2, 0], [102, 3.5]],
                   np.float32)
    np.testing.assert_array_equal(np.asarray(on_road(road, pts)), [1, 1, 1, 1, 0, 0, 0, 0])
    # a curved road: the bend's centreline is on it, 3 m outside the bend is not (rings stay within their shape)
    t = np.linspace(0, np.pi / 2, 60)
    arc = np.stack([30 * np.sin(t), 30 - 30 * np.cos(t)], -1).astype(np.float32)[None]
    curved = cond.road_from_lanes(arc, np.ones(arc.shape[:2], bool))
    mid = 30 * np.array([np.sin(np.pi / 4), 1 - np.cos(np.pi / 4)])
    outward = np.array([np.sin(np.pi / 4), -np.cos(np.pi / 4)])  # away from the arc's centre (0, 30)
    q = np.stack([mid, mid + 1.5 * outward, mid + 3.0 * outward, mid - 3.0 * outward]).astype(np.float32)
    np.testing.assert_array_equal(np.asarray(on_road(curved, q)), [1, 1, 0, 0])


def test_centres_corners_and_the_lane_distance_figure():
    lanes, ok = straight_lanes()
    # slot 0 (ego) and 1 on the lanes; slot 2 centre on the road but its 1.9 m-wide box sticks out of it (y=4.8:
    # edge at 5.25); slot 3 6 m beside the upper lane: off the road
    out = rollout([0.0, 3.5, 4.8, 9.5])
    r = cond.lane_offroad(out, PROMPT, H, lanes, ok)  # no road given: the lanes' own area (hand-drawn road)
    n = (T - H) * A
    assert r["positions"] == n and r["offroad_source"] == "given_lanes"
    assert r["offroad_share"] == pytest.approx(1 / 4)
    assert r["offroad_corner_share"] == pytest.approx(2 / 4)
    assert r["offroad_share_lane_distance"] == pytest.approx(1 / 4)
    assert r["mean_lane_distance_m"] == pytest.approx((0 + 0 + 1.3 + 6.0) / 4, rel=1e-5)
    # only generated, valid future positions count: hide slot 3's future and the result has no off-road centre
    out.valid[H:, 3] = False
    r = cond.lane_offroad(out, PROMPT, H, lanes, ok)
    assert r["positions"] == (T - H) * 3 and r["offroad_share"] == 0.0


def junction_road(lanes, lane_valid) -> RoadGeometry:
    """A store-like geometry: the lanes' strip (y in [-1.75, 5.25]) and a 20 x 20 m junction square beside it at
    x in [40, 60], y in [5.25, 25.25] with no lane through it."""
    g, v = 2, 4
    polygons = np.zeros((g, v, 2), np.float32)
    polygons[0] = [[0, -1.75], [100, -1.75], [100, 5.25], [0, 5.25]]
    polygons[1] = [[40, 5.25], [60, 5.25], [60, 25.25], [40, 25.25]]
    return RoadGeometry(polygons=polygons, polygon_valid=np.ones((g, v), bool),
                        polygon_kind=np.array([AREA_KIND_ID["lane"], AREA_KIND_ID["junction"]], np.int32),
                        edges=np.zeros((1, 2, 2), np.float32), edge_valid=np.zeros((1, 2), bool), lanes=lanes,
                        lane_valid=lane_valid)


def test_store_geometry_replaces_the_lane_distance_and_keeps_it_under_its_own_name():
    lanes, ok = straight_lanes()
    road = junction_road(lanes, ok)
    # slot 3 stands in the junction, 10 m from every lane centreline: on the road by the drivable area
    out = rollout([0.0, 3.5, 1.0, 15.0])
    r = cond.lane_offroad(out, PROMPT, H, lanes, ok, road)
    assert r["offroad_source"] == "store" and r["offroad_outside_geometry_share"] == 0.0
    assert r["offroad_share"] == 0.0 and r["offroad_corner_share"] == 0.0
    assert r["offroad_share_lane_distance"] == pytest.approx(1 / 4)
    # outside both the strip and the junction: off by both figures
    r = cond.lane_offroad(rollout([0.0, 3.5, 1.0, 15.0], x=70.0), PROMPT, H, lanes, ok, road)
    assert r["offroad_share"] == pytest.approx(1 / 4) and r["offroad_share_lane_distance"] == pytest.approx(1 / 4)
    # beyond the stored geometry's extent (x > 100 m): not judged by the area, counted as outside it
    r = cond.lane_offroad(rollout([0.0, 3.5, 1.0, 15.0], x=130.0), PROMPT, H, lanes, ok, road)
    assert np.isnan(r["offroad_share"]) and r["offroad_outside_geometry_share"] == 1.0
    # ...whereas a hand-drawn road's area is complete: past its end is off the road
    r = cond.lane_offroad(rollout([0.0, 3.5, 1.0, 15.0], x=130.0), PROMPT, H, lanes, ok)
    assert r["offroad_share"] == 1.0 and "offroad_outside_geometry_share" not in r
    # the jitted query compiles once for a road shape, whatever the positions
    before = cond._on_road._cache_size()
    cond.lane_offroad(rollout([1.0, 2.0, 3.0, 30.0], x=20.0), PROMPT, H, lanes, ok, road)
    assert cond._on_road._cache_size() == before


def test_store_without_geometry_reports_no_area_figure_and_names_the_rebuild():
    lanes, ok = straight_lanes()
    r = cond.lane_offroad(rollout([0.0, 3.5, 1.0, 15.0]), PROMPT, H, lanes, ok, None, source="none")
    assert np.isnan(r["offroad_share"]) and np.isnan(r["offroad_corner_share"])
    assert r["offroad_share_lane_distance"] == pytest.approx(1 / 4)
    assert "python -m gpd_jax.data build" in cond.OFFROAD_SOURCES[r["offroad_source"]]
    with pytest.raises(ValueError, match="source must be one of"):
        cond.lane_offroad(rollout([0.0] * A), PROMPT, H, lanes, ok, source="lanes")
    # nothing generated: every figure NaN, no positions
    empty = rollout([0.0] * A)
    empty.valid[:] = False
    r = cond.lane_offroad(empty, PROMPT, H, lanes, ok)
    assert r["positions"] == 0 and np.isnan(r["offroad_share"]) and np.isnan(r["offroad_share_lane_distance"])


class _FakeTokenizer:
    """Decodes a frame's tokens to one of three fixed sets of 50 lines of 20 points (by its first token)."""

    def __init__(self):
        rng = np.random.default_rng(0)
        x = np.linspace(-20.0, 20.0, 20)
        self.lines = np.stack([np.stack([np.broadcast_to(x, (50, 20)), rng.normal(0, 6, (50, 1)) + 0 * x], -1)
                               for _ in range(3)]).astype(np.float32)  # [3, 50, 20, 2]
        self.logits = rng.normal(0, 2, (3, 50)).astype(np.float32)

    def decode_tokens(self, tokens):
        i = np.asarray(tokens)[..., 0] % 3
        return self.lines[i], self.logits[i]


def test_prompt_map_scores_of_a_batch_in_one_call_equal_the_per_scenario_sums(monkeypatch):
    """The prompt evaluation scores the maps of every prompt and scenario of a batch in one compiled call (one
    trace for equal shapes); its per-prompt sums are those of the scenarios one by one."""
    import chex
    import jax

    from gpd_jax.metrics.map import map_metric_sums

    monkeypatch.setattr(cond, "_map_metric_sums", jax.jit(chex.assert_max_traces(map_metric_sums, n=2),
                                                          static_argnames=("step_axis",)))
    tok, (lanes, valid) = _FakeTokenizer(), straight_lanes()
    rng = np.random.default_rng(1)
    K, R, F = 2, 3, 2  # prompts, scenarios, frames
    tokens = rng.integers(0, 3, (K, R, F, 4))
    poses = np.concatenate([rng.uniform(0, 100, (K, R, F, 1)), rng.uniform(-2, 5, (K, R, F, 1)),
                            rng.uniform(-0.3, 0.3, (K, R, F, 1))], -1).astype(np.float32)
    gts = [[cond.vector_lanes_frames(lanes, valid, poses[q, r]) for r in range(R)] for q in range(K)]
    gt = np.stack([np.stack([g[0] for g in row]) for row in gts])
    ok = np.stack([np.stack([g[1] for g in row]) for row in gts])
    for _ in range(2):  # the second batch reuses the compiled call
        batched = cond.decoded_map_sums(tok, tokens, gt, ok, step_axis=0)
    for q in range(K):
        one_by_one = [cond.lane_map_sums(tok, tokens[q, r], poses[q, r], lanes, valid) for r in range(R)]
        for key, v in batched.items():
            want = sum(s[key][0] for s in one_by_one)
            np.testing.assert_allclose(v[q], want, rtol=1e-5, atol=1e-5 * (1 + abs(want)))
    assert batched["tp"].shape == (K,) and batched["tp"].sum() > 0
