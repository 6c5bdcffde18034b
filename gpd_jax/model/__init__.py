"""The GPD-1 transformer and its parts: agent tokenizer, block-causal attention, the native CPU kernel.

Public names (pure functions of an NNX module; `gpd_jax.checkpoint.build_model` builds one from a config):

* `GPD`: the NNX module (parameters, embeddings, heads).
* `forward(model, tokens)`: teacher-forced pass over whole frames, memory-linear attention.
* `forward_cached(model, tokens, cache, start_frame)`: a block of frames appended to a KV cache.
* `Prediction`, `KVCache`: what the heads return and what the cache holds.
"""

from gpd_jax.model.transformer import GPD, KVCache, Prediction, count_params, forward, forward_cached

__all__ = ["GPD", "KVCache", "Prediction", "count_params", "forward", "forward_cached"]
