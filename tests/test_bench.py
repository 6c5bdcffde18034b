"""The benchmark's JSON says where its figures come from (machine, kernel build, auto's choices)."""

import json
import os
import subprocess
import sys

import pytest


def test_bench_records_machine_build_and_auto_choice(tmp_path):
    out = tmp_path / "bench.json"
    env = dict(os.environ, GPD_JAX_CACHE=str(tmp_path / "cache"))
    env.pop("GPD_JAX_DECODE_ATTENTION", None)
    cmd = [sys.executable, "-m", "gpd_jax.bench", "rollout", "--config", "configs/gpd_tiny.py:test", "--batch", "1", "2",
           "--future-frames", "2", "--recompute-points", "2", "--repeats", "1", "--matmul-size", "256",
           "--copy-mib", "8", "--decode-attention", "auto", "xla", "--workload", "3", "--json", str(out)]
    res = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=600,
                         cwd=os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    assert res.returncode == 0, res.stderr[-3000:]
    rec = json.loads(out.read_text())
    machine = rec["machine"]
    for field in ("cpu", "isa", "cpu_count", "usable_cores", "jax", "backend"):
        assert machine[field] not in (None, ""), field
    assert "machine:" in res.stdout and machine["isa"] in res.stdout
    auto = [r for r in rec["runs"] if r["decode_attention"].startswith("auto->")]
    xla = [r for r in rec["runs"] if r["decode_attention"] == "xla"]
    assert len(auto) == 2 and len(xla) == 2
    for r in auto:
        assert r["auto_choices"], r
        for c in r["auto_choices"]:
            assert c["choice"] in ("native", "xla", "xla_batched") and c["why"]  # the fastest candidate wins
        if "native" in r["decode_attention"]:
            assert r["native_march"] and r["native_vector_width"] in (4, 8, 16)
    assert "auto chose" in res.stdout
    # the roofline: both peaks measured in the same run, useful bytes and FLOPs, compiled memory, the cache
    assert rec["matmul_gflops"] > 0 and rec["matmul_bf16_gflops"] > 0 and rec["copy_gbps"] > 0
    for r in rec["runs"]:
        assert r["decode_dtype"] == "float32"  # "auto" on a CPU
        assert r["bytes_per_scenario"] > r["kv_cache_bytes_per_scenario"] > 0
        assert r["achieved_gbps"] == pytest.approx(r["bytes_per_scenario"] / r["cached_s_per_scenario"] / 1e9)
        assert 0 < r["achieved_over_copy"] and 0 < r["achieved_over_matmul_bf16"]
        mem = r["memory"]
        assert mem["peak_bytes"] >= mem["temp_bytes"] > 0
        assert mem["peak_bytes_per_scenario"] == pytest.approx(mem["peak_bytes"] / (r["batch"] // r["devices"]))
        w = r["workload"]
        if r["batch"] == 2:  # the largest batch times 3 scenarios x 6 tasks in calls of 2
            assert w["rollouts"] == 18 and w["calls"] == 9 and w["seconds"] > 0
        else:
            assert w is None
    # the recompute baseline is the fastest full-prefix forward: both attentions timed at every prefix length
    rows = rec["recompute_forward"]
    assert [r["frames"] for r in rows] == sorted({r["frames"] for r in rows}) and len(rows) == 2
    for r in rows:
        assert r["dense_s"] > 0 and r["chunked_s"] > 0
        assert r["fastest"] == min(("dense", "chunked"), key=lambda k: r[f"{k}_s"])
    b1 = [r for r in rec["runs"] if r["batch"] == 1]
    assert all(r["speedup"] == pytest.approx(r["recompute_s_per_scenario"] / r["cached_s_per_scenario"]) for r in b1)
    if any(c["source"] == "measured" for r in auto for c in r["auto_choices"]):
        assert list((tmp_path / "cache" / "decode-attention").glob("*.json"))


def test_realism_bench_prints_and_records_seconds_per_scenario(tmp_path, capsys):
    from gpd_jax import bench

    out = tmp_path / "realism.json"
    assert bench.main(["realism", "--rollouts", "2", "--agents", "4", "--scenarios", "2", "--repeats", "1",
                       "--json", str(out)]) == 0
    rec = json.loads(out.read_text())
    assert rec["rollouts"] == 2 and rec["agents"] == 4 and rec["scenarios"] == 2 and rec["machine"]["cpu"]
    assert set(rec["rules"]) == {"official", "corrected"}  # both counting rules, each timed
    for r in rec["rules"].values():
        assert r["s_per_scenario"] > 0 and 0 < r["metametric"] <= 1 and r["road_edge_inexact_share"] == 0
    printed = capsys.readouterr().out
    assert "official rules" in printed and "corrected rules" in printed and "s per scenario" in printed


def test_precision_bench_keeps_bfloat16_rollouts_near_float32(tmp_path):
    """The default model's rollouts of 4 stored scenes under every task, 8 s, with a bfloat16 KV cache and decode
    attention against float32. Tolerances: one step (1 s) moves an agent by at most 1 mm (bf16 keeps 8 bits of
    mantissa: about 0.2 % of the attention inputs; 0.1 mm measured), and the closed loop's feedback grows that to
    a mean of at most 10 cm over 8 s (3 cm measured at 8 s); validity and map tokens agree almost everywhere, and
    the mean distance from the log (what ADE is made of) moves by under 2 % (0.4 % at most on 120 held-out scenes)."""
    from data_fixtures import write_small_store
    from gpd_jax import bench

    write_small_store(str(tmp_path / "store"), n_shards=2, per_shard=2, split="test")
    out = tmp_path / "precision.json"
    assert bench.main(["precision", "--data", str(tmp_path / "store"), "--json", str(out)]) == 0
    d = json.loads(out.read_text())["bfloat16_vs_float32"]
    first = d["all"]["xy_m_by_horizon"]["1s"]
    assert 0 < first["max"] < 1e-3, first  # different (bf16 ran), and close
    assert d["all"]["xy_m"]["mean"] < 0.1 and d["all"]["valid_agree"] > 0.999 and d["all"]["map_token_agree"] > 0.99
    assert d["map_prediction"]["xy_m"]["max"] == 0  # agents from the log: only map tokens may differ
    for name in ("scene_generation", "traffic_simulation", "closed_loop"):  # figures move by well under 2 %
        f32, bf16 = d[name]["from_log_m"]["float32"], d[name]["from_log_m"]["bfloat16"]
        assert f32 > 0 and abs(bf16 - f32) <= 0.02 * f32, (name, f32, bf16)
