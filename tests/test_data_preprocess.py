"""Preprocessing RawLog -> samples: frame convention, nearest-32 selection, validity, SUMO conversions."""

from collections import Counter

import numpy as np
import pytest

from data_fixtures import THETA, straight_road_log
from gpd_jax.data import preprocess as pp
from gpd_jax.data.sources import sumo_traffic
from gpd_jax.scene import TYPE_ID


def test_sample_shapes_and_frame_convention():
    log = straight_road_log()
    st = Counter()
    s = pp.make_sample(log, 5, 0, stats=st)
    for k, (shape, dtype) in pp.SAMPLE_SPEC.items():
        assert s[k].shape == shape and s[k].dtype == np.dtype(dtype), k
    c = 20
    # ego at the origin with heading 0 at the current frame, driving along +x at 10 m/s
    np.testing.assert_allclose(s["xy"][c, 0], 0.0, atol=1e-5)
    np.testing.assert_allclose(s["heading"][:, 0], 0.0, atol=1e-6)
    np.testing.assert_allclose(s["xy"][:, 0, 0], (np.arange(101) - c) * 1.0, atol=1e-4)
    np.testing.assert_allclose(s["xy"][:, 0, 1], 0.0, atol=1e-4)
    np.testing.assert_allclose(s["ego_pose"][:, :2], s["xy"][:, 0], atol=1e-6)
    assert s["valid"][:, 0].all() and s["agent_type"][0] == TYPE_ID["ego"]
    # lanes are in the scene frame too: the road's lanes run along x at y in {-3.5, 0, 3.5}
    pv = s["polyline_valid"]
    ys = np.unique(np.round(s["polylines"][..., 1][pv & (np.abs(s["polylines"][..., 0]) < 30)], 1))
    assert set(ys) >= {-3.5, 0.0, 3.5}
    # clipped to what the 64 m window sees over the sample (plus margin), resampled at 1 m
    xs = s["polylines"][..., 0][pv]
    assert xs.min() > -20 - 32 * np.sqrt(2) - 2 and xs.max() < 80 + 32 * np.sqrt(2) + 2
    pts = s["polylines"][0][pv[0]]
    np.testing.assert_allclose(np.linalg.norm(np.diff(pts, axis=0), axis=-1)[:-1], 1.0, atol=1e-3)


def test_nearest_32_and_validity_tracking():
    log = straight_road_log(num_others=40)
    st = Counter()
    s = pp.make_sample(log, 0, 0, pp.SampleConfig(agent_radius=1000.0), stats=st)
    c = 20
    # tracks are 6, 9, 12, ... m ahead; the 32 nearest valid at frame 20 are tracks 1..32 in order
    np.testing.assert_allclose(s["xy"][c, 1:, 0], 6.0 + 3.0 * np.arange(32), atol=1e-4)
    assert s["size"][3, 0] == 12.0 and s["agent_type"][3] == TYPE_ID["bus"]
    # track 1 vanishes from log frame 60 on; window starts at 0
    assert s["valid"][:60, 1].all() and not s["valid"][60:, 1].any()
    # track 2's NaN at frame 10 becomes an invalid frame and is counted
    assert not s["valid"][10, 2] and s["valid"][11, 2]
    assert st["agent_frames_nonfinite"] == 1
    assert np.isfinite(s["xy"]).all() and (s["xy"][~s["valid"]] == 0).all()
    # the late track (valid only from frame 100) is never selected
    assert s["valid"][:, 1:].any(0).sum() == 32


def test_radius_and_padding():
    s = pp.make_sample(straight_road_log(), 0, 0, pp.SampleConfig(agent_radius=20.0))
    # tracks at 6, 9, ..., 18 m: 5 vehicles, slots beyond are padding
    assert s["valid"][20, 1:6].all() and not s["valid"][:, 6:].any()
    assert (s["size"][6:] == 0).all() and (s["agent_type"][6:] == TYPE_ID["other"]).all()


def test_out_of_range_agents_are_invalidated_and_counted():
    st = Counter()
    s = pp.make_sample(straight_road_log(), 0, 0, pp.SampleConfig(agent_radius=1000.0, max_coord=90.0), stats=st)
    assert st["agent_frames_out_of_range"] > 0
    assert (np.abs(s["xy"][s["valid"]]) < 90.0).all()
    st = Counter()
    assert pp.make_sample(straight_road_log(), 0, 0, pp.SampleConfig(max_coord=70.0), stats=st) is None
    assert st["skip_ego_out_of_range"] == 1


def test_ego_not_present_is_skipped():
    log = straight_road_log()
    st = Counter()
    assert pp.make_sample(log, 0, 1, stats=st) is None  # track 1 vanishes at frame 60
    assert st["skip_ego_not_present"] == 1


def test_windows_and_iter_samples_deterministic():
    log = straight_road_log()
    cfg = pp.SampleConfig(min_neighbours=2)
    a = [sid for sid, _ in pp.iter_samples(log, cfg, num=5, seed=3)]
    b = [sid for sid, _ in pp.iter_samples(log, cfg, num=5, seed=3)]
    assert a == b and len(set(a)) == 5


def test_bumper_to_centre_and_compass():
    front = np.array([[10.0, 0.0], [10.0, 0.0], [10.0, 0.0], [0.0, 0.0]])
    compass = np.array([90.0, 0.0, 180.0, 45.0])  # east, north, south, north-east
    centre, h = sumo_traffic.bumper_to_centre(front, compass, np.array([4.0, 4.0, 4.0, 2.0 * np.sqrt(2)]))
    np.testing.assert_allclose(h, [0.0, np.pi / 2, -np.pi / 2, np.pi / 4], atol=1e-12)
    np.testing.assert_allclose(centre, [[8.0, 0.0], [10.0, -2.0], [10.0, 2.0], [-1.0, -1.0]], atol=1e-12)


def test_fcd_parsing(tmp_path):
    f = tmp_path / "fcd.csv"
    # time;id;x;y;angle;speed  (front bumpers); vehicle 7 is a 12 m bus heading west
    f.write_text("timestep_time;vehicle_id;vehicle_x;vehicle_y;vehicle_angle;vehicle_speed\n"
                 "100.00;3;10.0;5.0;90.0;1.0\n100.00;7;50.0;0.0;270.0;2.0\n"
                 "100.10;3;10.1;5.0;90.0;1.0\n")
    raw = sumo_traffic._fcd_to_rawlog(str(f), {"3": "g_car", "7": "g_bus"}, "x", "loc", sumo_traffic.SimConfig())
    assert raw.agent_ids == ("3", "7") and raw.num_frames == 2
    np.testing.assert_allclose(raw.agent_xy[0, 0], [10.0 - 2.3, 5.0])
    np.testing.assert_allclose(raw.agent_xy[0, 1], [56.0, 0.0], atol=1e-9)
    np.testing.assert_allclose(raw.agent_heading[0], [0.0, -np.pi], atol=1e-12)
    assert raw.agent_valid.tolist() == [[True, True], [True, False]]
    assert raw.agent_type.tolist() == [TYPE_ID["car"], TYPE_ID["bus"]]
    np.testing.assert_allclose(raw.agent_size[1], [12.0, 2.55])


@pytest.mark.parametrize("theta", [0.0, THETA])
def test_to_frame_inverse(theta):
    pose = np.array([3.0, -2.0, theta])
    p = np.array([[3.0 + np.cos(theta), -2.0 + np.sin(theta)]])
    np.testing.assert_allclose(pp.to_frame(p, pose), [[1.0, 0.0]], atol=1e-12)


def test_malformed_and_empty_logs():
    import dataclasses

    from gpd_jax.data.errors import DataError
    log = straight_road_log()
    bad = dataclasses.replace(log, agent_heading=log.agent_heading[:, :3])
    with pytest.raises(DataError, match="straight: bad RawLog: agent_heading shape"):
        list(pp.iter_samples(bad))
    empty = dataclasses.replace(log, agent_xy=np.zeros((0, 0, 2)), agent_heading=np.zeros((0, 0)),
                                agent_valid=np.zeros((0, 0), bool), agent_size=np.zeros((0, 2)),
                                agent_type=np.zeros((0,), np.int32), agent_ids=(), timestamps=np.zeros(0))
    with pytest.raises(DataError, match="empty log"):
        list(pp.iter_samples(empty))
    st = Counter()
    short = dataclasses.replace(log, agent_xy=log.agent_xy[:50], agent_heading=log.agent_heading[:50],
                                agent_valid=log.agent_valid[:50], timestamps=log.timestamps[:50])
    assert list(pp.iter_samples(short, stats=st)) == [] and st["skip_log_too_short"] == 1
