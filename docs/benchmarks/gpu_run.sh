#!/bin/bash
# The GPU figures of docs/benchmarks.md ("Roofline, memory and precision"), one run on one GPU (about 6 minutes on
# an H200): today's xla_batched path in fp32 and bf16, the cuDNN path at batches 512 to 4096 with the
# 1,000 scenarios x 6 tasks workload, bf16 against fp32 rollouts of the default model on data/test, and the
# defaults (auto attention, auto dtype) at batch 4096. JSONs and logs go to OUT (default: runs/gpu-bench).
#
#     bash docs/benchmarks/gpu_run.sh [OUT]
set -u
OUT=${1:-runs/gpu-bench}
mkdir -p "$OUT"
export PYTHONUNBUFFERED=1 XLA_PYTHON_CLIENT_MEM_FRACTION=.95
nvidia-smi -L
B="python3 -m gpd_jax.bench rollout --config configs/gpd_paper.py --repeats 2 --matmul-size 8192 --copy-mib 1024"
$B --decode-attention xla_batched --decode-dtype float32 bfloat16 --batch 256 --json "$OUT/gpu_xla.json" 2>&1 \
    | tee "$OUT/gpu_xla.log"
$B --decode-attention cudnn --decode-dtype bfloat16 --batch 512 2048 4096 --workload 1000 \
    --json "$OUT/gpu_cudnn.json" 2>&1 | tee "$OUT/gpu_cudnn.log"
python3 -m gpd_jax.bench precision --data data/test --json "$OUT/gpu_precision.json" 2>&1 | tee "$OUT/gpu_precision.log"
$B --decode-attention auto --batch 4096 --json "$OUT/gpu_auto.json" 2>&1 | tee "$OUT/gpu_auto.log"
