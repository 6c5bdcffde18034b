"""Native CPU kernels: built on first use with the system C++ compiler and registered as XLA FFI targets.

The only kernel is the fused block-causal attention of the KV-cached rollout
(`gpd_jax/model/kernels/block_causal_attention.cc`, semantics of `attention.attend_dynamic`). XLA:CPU cannot fuse a
dot with a softmax, so the pure-XLA decode step is memory-bound and single-threaded; the kernel keeps score
tiles in cache and uses the intra-op thread pool (see `python -m gpd_jax.bench rollout --decode-attention native xla`).

The shared library is compiled once per source, compiler flags, JAX version and CPU into
`$GPD_JAX_CACHE` (default `~/.cache/gpd_jax/kernels`), written to a temporary file and renamed. When no
compiler is found or the build fails, `available()` is False (with a warning saying why) and attention uses
the pure-XLA path, which gives the same results. `GPD_JAX_NATIVE=0` disables the kernel.
"""

from __future__ import annotations

import ctypes
import hashlib
import os
import platform
import shutil
import subprocess
import tempfile
import threading
import warnings
from pathlib import Path

import jax
import jax.numpy as jnp

TARGET = "gpd_block_causal_attention"
_SOURCE = Path(__file__).parent / "kernels" / "block_causal_attention.cc"
# -fassociative-math (without the rest of -ffast-math, so infinities keep their meaning) lets the max and sum
# reductions vectorize.
_FLAGS = ("-O3", "-march=native", "-std=c++17", "-shared", "-fPIC", "-pthread", "-fno-math-errno",
          "-fassociative-math", "-fno-signed-zeros", "-fno-trapping-math")
_lock = threading.Lock()
_state: dict = {}


def _cpu_id() -> str:
    try:
        with open("/proc/cpuinfo") as f:
            lines = [ln for ln in f if ln.startswith(("model name", "flags"))][:2]
        return "".join(lines)
    except OSError:
        return platform.processor()


def _cache_dir() -> Path:
    return Path(os.environ.get("GPD_JAX_CACHE", Path.home() / ".cache" / "gpd_jax" / "kernels"))


def build(compiler: str | None = None) -> Path:
    """Compiles the kernel (or finds it in the cache) and returns the shared library's path.

    Raises RuntimeError naming the compiler and its output when the build fails."""
    compiler = compiler or os.environ.get("CXX") or shutil.which("c++") or shutil.which("g++")
    if not compiler:
        raise RuntimeError("no C++ compiler found (set CXX or install g++)")
    src = _SOURCE.read_bytes()
    include = jax.ffi.include_dir()
    key = hashlib.sha256(b"\0".join([src, " ".join(_FLAGS).encode(), compiler.encode(),
                                     jax.__version__.encode(), _cpu_id().encode()])).hexdigest()[:16]
    out = _cache_dir() / f"block_causal_attention-{key}.so"
    if out.exists():
        return out
    out.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(suffix=".so", dir=out.parent)
    os.close(fd)
    cmd = [compiler, *_FLAGS, f"-I{include}", str(_SOURCE), "-o", tmp]
    try:
        res = subprocess.run(cmd, capture_output=True, text=True)
        if res.returncode != 0:
            raise RuntimeError(f"building {_SOURCE.name} failed ({' '.join(cmd)}):\n{res.stderr[-2000:]}")
        os.replace(tmp, out)
    finally:
        if os.path.exists(tmp):
            os.remove(tmp)
    return out


def available() -> bool:
    """Whether the native attention kernel is built and registered for the CPU platform (built on first call)."""
    with _lock:
        if "ok" not in _state:
            _state["ok"] = _load()
        return _state["ok"]


def _load() -> bool:
    if os.environ.get("GPD_JAX_NATIVE", "1").lower() in ("0", "false", "no", "off"):
        return False
    try:
        lib = ctypes.cdll.LoadLibrary(str(build()))
        jax.ffi.register_ffi_target(TARGET, jax.ffi.pycapsule(lib.GpdBlockCausalAttention), platform="cpu")
    except Exception as e:  # noqa: BLE001 - any failure means: use the XLA path, and say why
        warnings.warn(f"gpd_jax: native attention kernel unavailable, using the XLA path: {e}", stacklevel=2)
        return False
    return True


def block_causal_attention(q, k, v, q_frame, num_chunks, tokens_per_frame: int, chunk_len: int):
    """The FFI call. q f32[..., H, Sq, Dh] (pre-scaled), k, v f32[..., H, S, Dh], q_frame i32[..., Sq],
    num_chunks i32[...] -> f32[..., H, Sq, Dh]. Batches under `vmap` by passing the batch dims through."""
    call = jax.ffi.ffi_call(TARGET, jax.ShapeDtypeStruct(q.shape, q.dtype), vmap_method="broadcast_all")
    return call(q, k, v, jnp.asarray(q_frame, jnp.int32), jnp.asarray(num_chunks, jnp.int32),
                tokens_per_frame=int(tokens_per_frame), chunk_len=int(chunk_len))
