"""`python -m gpd_jax.data pack`: a packed store gives a model exactly the view the original gives, is smaller,
records what it dropped, and refuses models that would read what it cleared."""

import os
import tarfile

import numpy as np
import pytest

from data_fixtures import write_small_store
from gpd_jax.data import __main__ as data_cli
from gpd_jax.data.errors import DataError
from gpd_jax.data.loader import SplitSource
from gpd_jax.data.pack import check_packed, kept_frames, pack_store, packed_record
from gpd_jax.data.roadgeom import MAP_EDGE_KEYS, ROAD_KEYS
from gpd_jax.data.store import read_manifest
from gpd_jax.spec import ModelSpec

SPEC = ModelSpec(num_frames=11, num_history=3, num_agents=17, num_map_tokens=64, frame_stride=10,
                 velocity_inputs=True)


def _extract(archive: str, dest) -> None:
    with tarfile.open(archive) as tf:
        names = tf.getnames()
        assert all(not n.startswith(("/", "..")) and ".." not in n.split("/") for n in names)
        tf.extractall(dest, **({"filter": "data"} if hasattr(tarfile, "data_filter") else {}))


@pytest.fixture(scope="module")
def stores(tmp_path_factory):
    d = tmp_path_factory.mktemp("pack")
    src = str(d / "small")
    write_small_store(src, n_shards=2, per_shard=3, split="train")
    write_small_store(src, n_shards=1, per_shard=2, split="val", offset=0.5)
    archive = pack_store(src, str(d / "packs"), splits=["train"], frame_stride=10, num_agents=17, drop_road=True,
                         log=lambda _m: None)
    _extract(archive, d / "there")
    return src, str(d / "there" / "small"), archive


def test_kept_frames_are_the_model_frames_and_the_one_before_each():
    k = kept_frames(31, 10)
    assert np.flatnonzero(k).tolist() == [0, 9, 10, 19, 20, 29, 30]
    assert kept_frames(5, None).all()


def test_a_models_view_of_the_packed_store_is_the_original_view(stores):
    from gpd_jax.data.loader import to_scene

    src, packed, _ = stores
    a, b = SplitSource(src, "train", with_polylines=True), SplitSource(packed, "train", with_polylines=True)
    assert len(a) == len(b) == 6
    for i in range(len(a)):
        ra, rb = a[i], b[i]
        va = SPEC.view(to_scene({k: v[None] for k, v in ra.items()}))
        vb = SPEC.view(to_scene({k: v[None] for k, v in rb.items()}))
        for f in ("xy", "heading", "valid", "velocity", "map_tokens", "ego_pose", "size", "agent_type",
                  "polylines", "polyline_valid"):
            np.testing.assert_array_equal(np.asarray(getattr(va, f)), np.asarray(getattr(vb, f)), err_msg=f)
        assert np.asarray(va.valid).any() and np.isfinite(np.asarray(va.velocity)).any()
        # what it left out: the unread frames and slots are cleared, the road geometry is gone
        assert not rb["valid"][5].any() and not rb["valid"][:, 17:].any() and ra["valid"][5].any()
        assert vb.road is None


def test_the_pack_records_what_it_dropped_and_is_smaller(stores):
    src, packed, archive = stores
    rec = packed_record(packed)
    assert rec["frame_stride"] == 10 and rec["num_agents"] == 17 and rec["splits"] == ["train"]
    assert rec["dropped_keys"] == sorted(ROAD_KEYS + MAP_EDGE_KEYS) and rec["source"] == os.path.abspath(src)
    man = read_manifest(packed)
    assert set(man["splits"]) == {"train"} and man["num_samples"] == 6
    assert not set(ROAD_KEYS + MAP_EDGE_KEYS) & set(man["keys"])
    assert not os.path.exists(os.path.join(packed, "val"))
    raw = sum(os.path.getsize(os.path.join(r, f)) for r, _, fs in os.walk(os.path.join(src, "train")) for f in fs)
    assert os.path.getsize(archive) < 0.5 * raw
    assert packed_record(src) is None


def test_models_that_would_read_cleared_frames_or_slots_are_refused(stores):
    src, packed, _ = stores
    check_packed(packed, 10, 17)
    check_packed(packed, 20, 8)  # a multiple of the stride, fewer slots: it reads only kept frames
    check_packed(src, 3, 33)  # an unpacked store: anything goes
    with pytest.raises(DataError, match="stride 10 .*stride 5 reads others"):
        check_packed(packed, 5, 17)
    with pytest.raises(DataError, match="keeps 17 agent slots, and the model has 33"):
        check_packed(packed, 10, 33)
    from gpd_jax.config import load_config
    from gpd_jax.evaluation.preflight import preflight
    from gpd_jax.spec import EvalError

    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    c = load_config(os.path.join(root, "configs", "gpd_tiny.py:test"))
    c.model.num_frames, c.model.num_history, c.model.num_agents = 11, 3, 17
    c.data.frame_stride = 5
    with pytest.raises(EvalError, match="packed store"):
        preflight(c, packed, "train", task_names=["traffic_simulation"])


def test_the_command_line_resumes_and_names_bad_input(stores, tmp_path, capsys):
    src, _, _ = stores
    out = str(tmp_path / "o")
    assert data_cli.main(["pack", src, "--out", out, "--splits", "train", "val", "--frame-stride", "10"]) == 0
    path = os.path.join(out, "small.tar.xz")
    mtime = os.path.getmtime(path)
    assert data_cli.main(["pack", src, "--out", out]) == 0  # kept, not written again
    assert os.path.getmtime(path) == mtime and "exists; kept" in capsys.readouterr().out
    assert data_cli.main(["pack", src, "--out", str(tmp_path / "p"), "--splits", "test"]) == 2
    assert "no split 'test' to pack" in capsys.readouterr().err
    assert data_cli.main(["pack", str(tmp_path / "nothing"), "--out", str(tmp_path / "p")]) == 2
    assert not os.path.exists(tmp_path / "p" / "nothing.tar.xz")
