"""Generated networks are new from seed to seed; the near-duplicate check finds a moved copy of a network."""

import os
import re

import numpy as np
import pytest

from gpd_jax.data import netgeom
from gpd_jax.data.__main__ import main
from gpd_jax.data.errors import DataError
from gpd_jax.data.sources import sumo, sumo_networks


def _fingerprints_by_layout(out_dir: str, seed: int, per_layout: int = 2) -> dict[str, list]:
    jobs = sumo.plan_sumo_jobs(3 * per_layout, seed, None, per_job=1)
    index = sumo.prepare_networks(jobs, out_dir)
    by: dict[str, list] = {}
    for fp in netgeom.store_fingerprints(out_dir):
        by.setdefault(index[fp.name]["layout"], []).append(fp)
    return by


def test_generated_networks_differ_between_seeds_in_every_layout(tmp_path):
    a = _fingerprints_by_layout(str(tmp_path / "s7"), 7)
    b = _fingerprints_by_layout(str(tmp_path / "s11"), 11)
    assert set(a) == set(b) == {"grid", "spider", "random"}
    for layout in a:
        assert len(a[layout]) == len(b[layout]) == 2
        assert netgeom.near_duplicates(a[layout], b[layout]) == [], layout
        assert netgeom.near_duplicates(a[layout][:1], a[layout][1:]) == [], layout  # within one build too
        for x in a[layout]:
            for y in b[layout]:
                assert netgeom.geometry_distance(x, y) > 2 * netgeom.DEFAULT_TOL, (layout, x.name, y.name)


def test_same_spec_without_perturbation_is_a_near_duplicate(tmp_path):
    """What the seed-drawn shapes, jitter and perturbation prevent: netgenerate ignores --seed for grids."""
    base = sumo_networks.random_net_spec(3, "grid")
    fps = []
    for seed in (3, 4):
        spec = sumo_networks.NetSpec(**{**base.__dict__, "seed": seed, "perturb": 0.0, "jitter": 0.0})
        net = sumo_networks.generate_network(spec, str(tmp_path / f"g{seed}.net.xml"))
        fps.append(netgeom.fingerprint_network(net))
    assert netgeom.geometry_distance(*fps) < 0.1
    assert len(netgeom.near_duplicates(fps[:1], fps[1:])) == 1


def _moved_copy(src: str, dst: str, angle: float, offset) -> None:
    """Writes `src` with every coordinate rotated by `angle` and shifted by `offset` (a rigid motion)."""
    c, s = np.cos(angle), np.sin(angle)

    def pt(m):
        x, y = float(m.group(1)), float(m.group(2))
        return f"{c * x - s * y + offset[0]:.3f},{s * x + c * y + offset[1]:.3f}"

    text = sumo_networks._open_xml(src).read().decode()
    text = re.sub(r'shape="([^"]*)"', lambda m: 'shape="' + re.sub(r"(-?[\d.]+),(-?[\d.]+)(?:,-?[\d.]+)?", pt,
                                                                        m.group(1)) + '"', text)
    with open(dst, "w") as f:
        f.write(text)


@pytest.fixture
def net_and_copy(tmp_path):
    os.makedirs(tmp_path / "a")
    os.makedirs(tmp_path / "b")
    net = sumo_networks.generate_network(sumo_networks.random_net_spec(5, "spider"),
                                         str(tmp_path / "a" / "net.net.xml"))
    copy = str(tmp_path / "b" / "moved.net.xml")
    _moved_copy(net, copy, angle=0.9, offset=(1234.5, -321.0))
    return net, copy


def test_near_duplicate_check_catches_a_moved_copy(net_and_copy, tmp_path):
    net, copy = net_and_copy
    fa, fb = netgeom.fingerprint_network(net), netgeom.fingerprint_network(copy)
    assert not np.allclose(sumo_networks.read_network_lanes(net)[0][0], sumo_networks.read_network_lanes(copy)[0][0],
                           atol=100)
    assert fa.length == pytest.approx(fb.length, rel=1e-3)
    assert netgeom.geometry_distance(fa, fb) < 0.1
    assert netgeom.geometry_distance(fb, fa) < 0.1
    other = netgeom.fingerprint_network(sumo_networks.generate_network(sumo_networks.random_net_spec(6, "spider"),
                                                                       str(tmp_path / "c.net.xml")))
    found = netgeom.near_duplicates([fb, other], [fa])
    assert [(d["evaluated"], d["reference"]) for d in found] == [(copy, net)]
    # saved fingerprints and network files are accepted as they are
    netgeom.save_fingerprint(fa, str(tmp_path / "a.fp.npz"))
    assert len(netgeom.near_duplicates([copy], [str(tmp_path / "a.fp.npz")])) == 1


def test_build_refuses_a_moved_copy_across_splits(net_and_copy, tmp_path):
    net, copy = net_and_copy
    out = str(tmp_path / "ds")
    jobs = sumo.plan_sumo_jobs(2, 0, [net, copy], per_job=1)
    assert sorted(j.split for j in jobs) == ["test", "train"]
    with pytest.raises(DataError, match="nearly match") as e:
        sumo.build_sumo(out, 2, seed=0, nets=[net, copy], workers=1, per_job=1)
    assert "a_net" in str(e.value) and "b_moved" in str(e.value)
    assert not any(n.startswith("job_") for n in os.listdir(os.path.join(out, "_jobs")))  # nothing simulated
    # the check across stores: the copy against the store's train network, from the command line
    train = [loc for loc, r in netgeom.read_network_index(out).items() if r["split"] == "train"]
    test = str(tmp_path / "test.net.xml")
    _moved_copy(net if train == ["a_net"] else copy, test, angle=-2.0, offset=(10.0, 20.0))
    assert main(["near-duplicates", "--eval", test, "--reference", out]) == 1
    assert main(["near-duplicates", "--eval", out, "--reference", out]) == 1  # its test network vs its train one
    other = sumo_networks.generate_network(sumo_networks.random_net_spec(8, "spider"), str(tmp_path / "other.net.xml"))
    assert main(["near-duplicates", "--eval", test, "--reference", other]) == 0
