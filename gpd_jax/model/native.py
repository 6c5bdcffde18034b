"""Native CPU kernels: built on first use with the system C++ compiler and registered as XLA FFI targets.

The only kernel is the fused block-causal attention of the KV-cached rollout
(`gpd_jax/model/kernels/block_causal_attention.cc`, semantics of `attention.attend_dynamic`). XLA:CPU cannot fuse a
dot with a softmax, so the pure-XLA decode step is memory-bound and single-threaded; the kernel keeps score
tiles in registers and L1 and uses the intra-op thread pool (see `python -m gpd_jax.bench rollout
--decode-attention native xla`).

Build target: `-march=$GPD_JAX_NATIVE_MARCH` (default `native`, the CPU this runs on; `x86-64-v3` is AVX2,
`x86-64-v4` AVX-512, `x86-64` SSE2). The kernel's vector width follows the target at compile time. A build
for a target the CPU cannot run is refused (`runnable`), so it is never loaded.

The shared library is compiled once per source, compiler, flags (target included), JAX version and CPU into
`$GPD_JAX_CACHE` (default `~/.cache/gpd_jax/kernels`), written to a temporary file and renamed. When no
compiler is found or the build fails, `available()` is False (with a warning saying why) and attention uses
the pure-XLA path, which gives the same results. `GPD_JAX_NATIVE=0` disables the kernel.
"""

from __future__ import annotations

import ctypes
import hashlib
import os
import platform
import re
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
# reductions vectorize; -ffp-contract=fast makes a * b + c one FMA (GCC turns contraction off under -std=c++17).
_FLAGS = ("-O3", "-std=c++17", "-shared", "-fPIC", "-pthread", "-fno-math-errno", "-ffp-contract=fast",
          "-fassociative-math", "-fno-signed-zeros", "-fno-trapping-math")
_lock = threading.RLock()
_state: dict = {}  # "ok" (bool, the default target) and per-target entries "lib:<march>"

# x86-64 micro-architecture levels and the CPU flags (as /proc/cpuinfo spells them) each needs to run.
_X86_LEVELS = {
    "x86-64": (),
    "x86-64-v2": ("sse4_2", "popcnt", "ssse3"),
    "x86-64-v3": ("avx2", "fma", "bmi2", "f16c", "movbe"),
    "x86-64-v4": ("avx512f", "avx512bw", "avx512cd", "avx512dq", "avx512vl"),
}


def march() -> str:
    """The kernel's build target: `$GPD_JAX_NATIVE_MARCH`, default `native` (the CPU this runs on)."""
    return os.environ.get("GPD_JAX_NATIVE_MARCH", "").strip() or "native"


def disabled() -> bool:
    return os.environ.get("GPD_JAX_NATIVE", "1").lower() in ("0", "false", "no", "off")


def _cpuinfo() -> dict:
    try:
        with open("/proc/cpuinfo") as f:
            text = f.read()
    except OSError:
        return {}
    out = {}
    for key in ("model name", "flags", "Features", "CPU part", "CPU implementer"):
        m = re.search(rf"^{key}\s*:\s*(.*)$", text, re.M)
        if m:
            out[key] = m.group(1).strip()
    return out


def _cpu_id() -> str:
    info = _cpuinfo()
    if not info:
        return platform.processor() or platform.machine()
    return "\n".join(f"{k}: {v}" for k, v in info.items())


def cpu_flags() -> set[str]:
    info = _cpuinfo()
    return set((info.get("flags") or info.get("Features") or "").split())


def isa_level() -> str:
    """The CPU's vector instruction set: "avx512", "avx2", "avx", "sse", "neon" or the machine name."""
    flags = cpu_flags()
    if "avx512f" in flags:
        return "avx512"
    if "avx2" in flags:
        return "avx2"
    if "avx" in flags:
        return "avx"
    if "sse2" in flags:
        return "sse"
    if "asimd" in flags or platform.machine() in ("aarch64", "arm64"):
        return "neon"
    return platform.machine()


def machine_info() -> dict:
    """What a benchmark figure depends on: CPU model, instruction-set level, cores, JAX version."""
    info = _cpuinfo()
    try:
        usable = len(os.sched_getaffinity(0))
    except AttributeError:
        usable = os.cpu_count()
    return {"cpu": info.get("model name") or platform.processor() or platform.machine(),
            "machine": platform.machine(), "isa": isa_level(), "cpu_count": os.cpu_count(), "usable_cores": usable,
            "jax": jax.__version__, "jaxlib": getattr(jax.lib, "__version__", None) or _jaxlib_version(),
            "backend": jax.default_backend()}


def _jaxlib_version() -> str | None:
    try:
        import jaxlib

        return jaxlib.__version__
    except Exception:  # noqa: BLE001
        return None


def runnable(target: str | None = None) -> bool:
    """Whether this CPU can run code built for `-march=target` (known x86-64 levels are checked against the
    CPU's flags; `native` and unknown targets are assumed runnable)."""
    target = target or march()
    if target not in _X86_LEVELS:
        return True
    if platform.machine() not in ("x86_64", "AMD64"):
        return False
    flags = cpu_flags()
    levels = list(_X86_LEVELS)
    return all(f in flags for lv in levels[: levels.index(target) + 1] for f in _X86_LEVELS[lv])


def _compiler(compiler: str | None = None) -> str:
    compiler = compiler or os.environ.get("CXX") or shutil.which("c++") or shutil.which("g++")
    if not compiler:
        raise RuntimeError("no C++ compiler found (set CXX or install g++)")
    return compiler


def build_key(target: str | None = None, compiler: str | None = None) -> str:
    """The cache key of a build: source, compiler, flags and target, JAX version, CPU."""
    target = target or march()
    flags = (*_FLAGS, f"-march={target}")
    return hashlib.sha256(b"\0".join([_SOURCE.read_bytes(), " ".join(flags).encode(), _compiler(compiler).encode(),
                                      jax.__version__.encode(), _cpu_id().encode()])).hexdigest()[:16]


def _cache_dir() -> Path:
    return Path(os.environ.get("GPD_JAX_CACHE", Path.home() / ".cache" / "gpd_jax" / "kernels"))


def cache_dir() -> Path:
    """Where built kernels (and the measured `auto` choices of `gpd_jax.model.attention`) are kept."""
    return _cache_dir()


def build(compiler: str | None = None, target: str | None = None) -> Path:
    """Compiles the kernel for `-march=target` (default `march()`), or finds it in the cache, and returns the
    shared library's path. Raises RuntimeError naming the compiler and its output when the build fails."""
    compiler = _compiler(compiler)
    target = target or march()
    include = jax.ffi.include_dir()
    out = _cache_dir() / f"block_causal_attention-{build_key(target, compiler)}.so"
    if out.exists():
        return out
    out.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(suffix=".so", dir=out.parent)
    os.close(fd)
    cmd = [compiler, *_FLAGS, f"-march={target}", f"-I{include}", str(_SOURCE), "-o", tmp]
    try:
        res = subprocess.run(cmd, capture_output=True, text=True)
        if res.returncode != 0:
            raise RuntimeError(f"building {_SOURCE.name} failed ({' '.join(cmd)}):\n{res.stderr[-2000:]}")
        os.replace(tmp, out)
    finally:
        if os.path.exists(tmp):
            os.remove(tmp)
    return out


def _target_name(target: str) -> str:
    return f"{TARGET}_{re.sub(r'[^A-Za-z0-9_]', '_', target)}"


def load(target: str | None = None) -> dict | None:
    """Builds (or finds) and registers the kernel for `target` (default `march()`) once per process; returns
    {"target", "ffi_target", "path", "vector_width", "key"} or None (with a warning saying why) when it cannot
    be used here: disabled by GPD_JAX_NATIVE=0, no compiler, a failed build, or a target this CPU cannot run."""
    target = target or march()
    slot = f"lib:{target}"
    with _lock:
        if slot not in _state:
            _state[slot] = _load(target)
        return _state[slot]


def _load(target: str) -> dict | None:
    if disabled():
        return None
    try:
        if not runnable(target):
            raise RuntimeError(f"this CPU ({isa_level()}) cannot run code built for -march={target}")
        path = build(target=target)
        lib = ctypes.cdll.LoadLibrary(str(path))
        name = _target_name(target)
        jax.ffi.register_ffi_target(name, jax.ffi.pycapsule(lib.GpdBlockCausalAttention), platform="cpu")
        jax.ffi.register_ffi_target(name + "_bf16", jax.ffi.pycapsule(lib.GpdBlockCausalAttentionBf16),
                                    platform="cpu")
        width = int(lib.GpdAttentionVectorWidth())
    except Exception as e:  # noqa: BLE001 - any failure means: use the XLA path, and say why
        warnings.warn(f"gpd_jax: native attention kernel unavailable, using the XLA path: {e}", stacklevel=3)
        return None
    return {"target": target, "ffi_target": name, "path": str(path), "vector_width": width,
            "key": path.stem.rsplit("-", 1)[-1]}


def available(target: str | None = None) -> bool:
    """Whether the native attention kernel is built and registered for the CPU platform (built on first call)."""
    if target is None:
        with _lock:
            if "ok" not in _state:
                _state["ok"] = load() is not None
            return _state["ok"]
    return load(target) is not None


def build_info(target: str | None = None) -> dict | None:
    """The loaded build of `target` (see `load`) without building anything; None if not loaded."""
    return _state.get(f"lib:{target or march()}")


def block_causal_attention(q, k, v, q_frame, num_chunks, tokens_per_frame: int, chunk_len: int,
                           target: str | None = None):
    """The FFI call. q f32[..., H, Sq, Dh] (pre-scaled; other float dtypes are widened), k, v f32 or bf16
    [..., H, S, Dh] (a bfloat16 cache is read as such: half the bytes), q_frame i32[..., Sq], num_chunks i32[...]
    -> f32[..., H, Sq, Dh]. Batches under `vmap` by passing the batch dims through. `target`: which build
    (default `march()`); it must have been loaded (`available(target)`)."""
    lib = load(target)
    if lib is None:
        raise RuntimeError(f"the native attention kernel for -march={target or march()} is not available")
    if k.dtype != v.dtype or k.dtype not in (jnp.float32, jnp.bfloat16):
        raise ValueError(f"the native attention kernel reads a float32 or bfloat16 cache, got k {k.dtype}, "
                         f"v {v.dtype}")
    name = lib["ffi_target"] + ("_bf16" if k.dtype == jnp.bfloat16 else "")
    q = q.astype(jnp.float32)
    call = jax.ffi.ffi_call(name, jax.ShapeDtypeStruct(q.shape, jnp.float32), vmap_method="broadcast_all")
    return call(q, k, v, jnp.asarray(q_frame, jnp.int32), jnp.asarray(num_chunks, jnp.int32),
                tokens_per_frame=int(tokens_per_frame), chunk_len=int(chunk_len))
