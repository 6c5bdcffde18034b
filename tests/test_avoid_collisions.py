"""Collision-aware decoding (`RolloutOptions.avoid_collisions`, `gpd_jax.decoding.avoid_overlaps`): a car that would
run into the one ahead takes the free cell of its sampling head nearest its regressed state (a draw among the free
cells above temperature 0), the one ahead keeps its state, a pair already overlapping stays as it is, a box on the
road stays on it; the option is off by default and needs a sampling head."""

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import nnx

from gpd_jax.config import load_config
from gpd_jax.decoding import avoid_overlaps, rollout_prepared, top_cells
from gpd_jax.geometry import RoadGeometry
from gpd_jax.metrics.agents import box_overlap_pairwise
from gpd_jax.metrics.realism import box_signed_distance
from gpd_jax.model import GPD, Modes
from gpd_jax.options import RolloutOptions, Sampling
from gpd_jax.synthetic import synthetic_scenes
from gpd_jax.tasks import make_tasks

SIZE = jnp.asarray([[4.0, 2.0]] * 3, jnp.float32)
avoid_overlaps = jax.jit(avoid_overlaps, static_argnames=("sampling",))


def _queue():
    """Three cars heading +x: a rear car (0) at x = 0 whose next state (x = 9) would overlap the car ahead (1, at
    x = 10, staying), and a car (2) far to the side. Cells of each car: its next x at 9, 6, 3 (most likely first), all
    at y = 0; car 2's cells at its own y."""
    prev_xy = jnp.asarray([[0.0, 0.0], [10.0, 0.0], [0.0, 30.0]])
    xy = jnp.asarray([[9.0, 0.0], [10.0, 0.0], [9.0, 30.0]])
    heading = jnp.zeros(3)
    cell_x = jnp.asarray([9.0, 6.0, 3.0])
    cells_xy = jnp.stack([jnp.broadcast_to(cell_x, (3, 3)), jnp.asarray([[0.0] * 3, [0.0] * 3, [30.0] * 3])], -1)
    modes = Modes(logits=jnp.broadcast_to(jnp.asarray([2.0, 1.0, 0.0]), (3, 3)), xy=cells_xy,
                  heading=jnp.zeros((3, 3)), velocity=jnp.broadcast_to(cell_x[None, :, None] * 0.1, (3, 3, 2)),
                  scale=jnp.ones((3, 3, 5)), axes=jnp.zeros(3))
    return xy, heading, modes, prev_xy


def _overlap(xy_a, xy_b, heading_a=0.0):
    half = SIZE[0] / 2
    return float(box_signed_distance(xy_a, jnp.asarray(heading_a), half, xy_b, jnp.zeros(()), half)) < 0


def test_the_car_behind_brakes_to_the_free_cell_nearest_its_state_and_the_car_ahead_keeps_its_state():
    xy, heading, modes, prev_xy = _queue()
    vel = jnp.ones((3, 2))
    every = jnp.ones(3, bool)
    assert _overlap(xy[0], xy[1])  # what the decoding is for
    new_xy, new_h, new_v = avoid_overlaps(xy, heading, vel, modes, prev_xy, every, every, SIZE, every, None,
                                          Sampling(0.0))
    # x = 9 overlaps the car at 10 (4 m boxes); x = 6 (front bumper at 8, the other's rear at 8) does not: the free
    # cell nearest the regressed x = 9
    np.testing.assert_allclose(new_xy[0], [6.0, 0.0])
    # the nearest free cell, not the most likely one: with x = 3 the likelier, x = 6 is still taken
    likelier_far = modes._replace(logits=jnp.broadcast_to(jnp.asarray([2.0, 0.0, 1.0]), (3, 3)))
    near_xy, _, _ = avoid_overlaps(xy, heading, vel, likelier_far, prev_xy, every, every, SIZE, every, None,
                                   Sampling(0.0))
    np.testing.assert_allclose(near_xy[0], [6.0, 0.0])
    np.testing.assert_allclose(new_v[0], [0.6, 0.6])
    assert not _overlap(new_xy[0], new_xy[1])
    # the car ahead (the rear car is behind it) and the car to the side keep their states
    np.testing.assert_array_equal(new_xy[1:], xy[1:])
    np.testing.assert_array_equal(new_v[1:], vel[1:])
    np.testing.assert_array_equal(new_h, heading)
    # not movable (a slot given from the log): its state stays, overlap or not
    fixed, _, _ = avoid_overlaps(xy, heading, vel, modes, prev_xy, every, every, SIZE,
                                 jnp.asarray([False, True, True]), None, Sampling(0.0))
    np.testing.assert_array_equal(fixed, xy)
    # every cell blocked (the car ahead is right behind the rear car's cells): the state stays
    blocked = xy.at[1].set([4.5, 0.0])
    prev_blocked = prev_xy.at[1].set([4.5, 0.0])
    kept, _, _ = avoid_overlaps(blocked, heading, vel, modes, prev_blocked, every, every, SIZE, every, None,
                                Sampling(0.0))
    np.testing.assert_array_equal(kept[0], blocked[0])


def test_a_pair_whose_boxes_overlapped_at_the_frame_before_is_left_as_it_is():
    """A tight standing queue (or a log with overlapping boxes): no cell undoes the overlap, and taking a free one
    moved standing cars metres from their (right) regressed states."""
    xy, heading, modes, prev_xy = _queue()
    every = jnp.ones(3, bool)
    # the rear car stands at x = 7, its box (5..9) already over the car ahead's (8..12), and its regressed state stays
    stand_prev = prev_xy.at[0].set([7.0, 0.0])
    stand = xy.at[0].set([7.0, 0.0])
    assert _overlap(stand_prev[0], stand_prev[1]) and _overlap(stand[0], stand[1])
    kept, _, _ = avoid_overlaps(stand, heading, jnp.ones((3, 2)), modes, stand_prev, every, every, SIZE, every,
                                None, Sampling(0.0))
    np.testing.assert_array_equal(kept, stand)
    # the same state coming from behind (x = 0 at the frame before, clear of the car ahead) is still swapped
    swapped, _, _ = avoid_overlaps(stand, heading, jnp.ones((3, 2)), modes, prev_xy, every, every, SIZE, every, None,
                                   Sampling(0.0))
    np.testing.assert_allclose(swapped[0], [6.0, 0.0])


def test_a_draw_above_temperature_zero_lands_on_a_free_cell_and_a_box_on_the_road_stays_on_it():
    xy, heading, modes, prev_xy = _queue()
    every = jnp.ones(3, bool)
    draws, turns, _ = jax.vmap(lambda k: avoid_overlaps(xy, heading, jnp.ones((3, 2)), modes, prev_xy, every, every,
                                                        SIZE, every, k, Sampling(0.3)))(
        jax.random.split(jax.random.key(0), 64))
    assert all(not _overlap(d[0], xy[1], h[0]) for d, h in zip(draws, turns))
    picked = np.round(np.asarray(draws[:, 0, 0]) / 3) * 3  # cell 6 or 3 (+ noise of scale 0.3 m)
    assert set(picked.tolist()) <= {3.0, 6.0} and (picked == 6.0).mean() > 0.5  # 6 is the likelier free cell
    # a road x in [-10, x_end], y in [-5, 40] (its edge the ring itself): the rear car's box (x = 9 +- 2) is on it
    def road(x_end):
        ring = jnp.asarray([[-10.0, -5.0], [x_end, -5.0], [x_end, 40.0], [-10.0, 40.0]])
        return RoadGeometry(polygons=ring[None], polygon_valid=jnp.ones((1, 4), bool),
                            polygon_kind=jnp.zeros(1, jnp.int32), edges=jnp.concatenate([ring, ring[:1]])[None],
                            edge_valid=jnp.ones((1, 5), bool), lanes=jnp.zeros((1, 2, 2)),
                            lane_valid=jnp.zeros((1, 2), bool))

    def decode(m, r=None, at=xy):
        return avoid_overlaps(at, heading, jnp.ones((3, 2)), m, prev_xy, every, every, SIZE, every, None,
                              Sampling(0.0), r)[0][0]

    np.testing.assert_allclose(decode(modes, road(11.5)), [6.0, 0.0])
    # its free cells moved sideways off the road (y = -8): on the road before, it may not take them and stays
    off = modes._replace(xy=modes.xy.at[0, 1:, 1].set(-8.0))
    np.testing.assert_array_equal(decode(off, road(11.5)), xy[0])
    np.testing.assert_allclose(decode(off), [6.0, -8.0])  # without a road it would
    # alone on a road that ends at x = 10: its state (front corners at x = 11) leaves it, so it takes the cell
    # nearest its state that keeps its box on the road (x = 6), though nothing is in its way
    alone = xy.at[1].set([100.0, 100.0])
    np.testing.assert_allclose(decode(modes, road(10.0), alone), [6.0, 0.0])
    np.testing.assert_array_equal(decode(modes, None, alone), alone[0])


def test_top_cells_are_the_most_likely_first():
    xy, heading, modes, prev_xy = _queue()
    shuffled = jax.tree.map(lambda a: a[:, ::-1] if a.ndim > 1 else a, modes)
    top = top_cells(shuffled, 2)
    np.testing.assert_array_equal(top.xy[:, :, 0], np.broadcast_to([9.0, 6.0], (3, 2)))
    np.testing.assert_array_equal(top.logits, np.broadcast_to([2.0, 1.0], (3, 2)))


HEAD = ["--config.model.agent_bins=0.5", "--config.model.agent_bin_extent=(2.0, 1.0)",
        "--config.model.predict_delta=True", "--config.model.velocity_inputs=True"]


@pytest.fixture(scope="module")
def setup():
    cfg = load_config("configs/gpd_tiny.py:test", HEAD)
    m = cfg.model
    scenes = synthetic_scenes(0, 2, m.num_frames, m.num_history, m.num_agents, m.num_map_tokens, m.codebook_size)
    scenes = scenes.replace(velocity=np.zeros_like(scenes.xy))
    # the agents crowded together (a pair overlaps at the current frame, the others do not: a pair that already
    # overlaps is not tested), and every generated agent kept present (the validity head's bias raised), so the
    # decoding has something to do
    scenes = scenes.replace(xy=scenes.xy * 0.3)
    tasks = make_tasks(["traffic_simulation"], m.num_map_tokens, m.num_agents)
    model = GPD(m, nnx.Rngs(0))
    bias = model.valid_head.linears[-1].bias
    bias[...] = bias[...] + 20.0
    return cfg, model, jax.tree.map(jnp.asarray, scenes), jax.tree.map(jnp.asarray, tasks)


def test_the_rollout_option_is_off_by_default_compiles_once_and_agrees_between_the_two_rollouts(setup):
    cfg, model, scenes, tasks = setup
    h = cfg.model.num_history
    graphdef, state = nnx.split(model)
    key = jax.random.key(0)
    assert RolloutOptions().avoid_collisions is False
    with pytest.raises(ValueError, match="avoid_collisions"):
        RolloutOptions(avoid_collisions=1)
    crowded = scenes

    @jax.jit
    @chex.assert_max_traces(n=1)
    def fn(state, scenes, key):
        return rollout_prepared(nnx.merge(graphdef, state), scenes, tasks, key, h,
                                RolloutOptions(avoid_collisions=True))

    out = fn(state, crowded, key)
    fn(state, crowded, jax.random.key(1))
    plain = rollout_prepared(model, crowded, tasks, key, h, RolloutOptions())
    np.testing.assert_array_equal(out.xy[..., :h, :, :], plain.xy[..., :h, :, :])
    assert np.abs(np.asarray(out.xy) - np.asarray(plain.xy)).max() > 1e-3  # it changed something
    size = crowded.size[:, None]

    def overlapping(o):  # generated boxes overlapping another's in the future frames
        hit = box_overlap_pairwise(o.xy[:, 0, h:], o.heading[:, 0, h:], size, o.valid[:, 0, h:])
        return int(np.asarray(hit.any(-1)).sum())

    assert overlapping(out) < overlapping(plain)
    slow = rollout_prepared(model, crowded, tasks, key, h, RolloutOptions(avoid_collisions=True, method="recompute"))
    np.testing.assert_allclose(slow.xy, out.xy, atol=1e-3 * float(np.abs(out.xy).max()))
