"""GPD-1 map tokenizer: lane rasterizer, VQ-VAE (ResNet encoder, 128 x 128 codebook) and DETR lane decoder.

Public API:
  rasterize(polylines, valid, pose) -> f32[..., 256, 256]        (raster.py)
  load_tokenizer(checkpoint_dir) -> MapTokenizer                  (tokenizer.py)
    .codebook f32[K, D], .encode(params, rasters) -> i32[..., 64],
    .decode(params, tokens) -> (f32[..., 50, 20, 2], f32[..., 50])
  tokenizer_metrics(graphdef, params, config, batches) -> metrics (evaluation.py)
Stage-1 training is `gpd_jax.training.map_tokenizer` (`python train.py --config configs/map_tokenizer.py:tiny`).
CLI: gpd-jax tokenizer {evaluate,diagnose,encode,export,bench,netframes,pack-netframes}   (__main__.py)
"""

from gpd_jax.lazy import lazy_names

# imported on first use: `gpd-jax tokenizer` imports this package before it checks its arguments (no JAX yet)
__getattr__, __dir__ = lazy_names(__name__, {
    "gpd_jax.map_tokenizer.raster": ("rasterize",),
    "gpd_jax.map_tokenizer.tokenizer": ("MapTokenizer", "export_tokenizer", "load_tokenizer"),
})

__all__ = ["MapTokenizer", "export_tokenizer", "load_tokenizer", "rasterize"]
