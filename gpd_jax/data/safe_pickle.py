"""Loading pickles from user data without letting them run code.

A pickle is a program: every global it names is imported and may be called while it loads (`os.system`,
`builtins.exec`, any class's constructor). `load(path)` reads one with `SafeUnpickler`, whose `find_class`
hands out only an allow-list of globals that can rebuild plain data and cannot reach anything else:

* builtin containers and scalars (dict, list, tuple, set, frozenset, str, bytes, bytearray, int, float, complex,
  bool) under both their Python 3 (`builtins`) and protocol-0/2 (`__builtin__`) module names;
* `collections.OrderedDict` and `collections.defaultdict` (whose factory can itself only be an allowed global);
* `_codecs.encode`, restricted to the latin-1 encoding that protocols 0-2 use to store `bytes`;
* what numpy needs to rebuild arrays, dtypes and numpy scalars: `numpy.ndarray`, `numpy.dtype` and the
  `_reconstruct`, `scalar` and `_frombuffer` helpers under both `numpy.core` (numpy 1.x) and `numpy._core`
  (numpy 2.x) names. These are looked up in a fixed table; `find_class` never imports a module by name;
* `metadrive.scenario.scenario_description.ScenarioDescription`, a plain `dict` subclass older ScenarioNet files
  were pickled as, is rebuilt as a `dict` (MetaDrive itself is never imported).

Any other global is refused *before* it is called: `load` raises `DataError` naming the file and the global.
Truncated or corrupt files raise `DataError` too. Nothing in `gpd_jax.data` calls `pickle.load` on user data.
"""

from __future__ import annotations

import collections
import io
import os
import pickle
import struct

import numpy as np

from gpd_jax.data.errors import DataError


class ForbiddenGlobal(pickle.UnpicklingError):
    """A pickle named a global outside the allow-list (`module`, `name`)."""

    def __init__(self, module: str, name: str):
        self.module, self.name = module, name
        super().__init__(f"forbidden global {module}.{name}")


def _latin1_encode(obj, encoding="utf-8", errors="strict"):
    """`_codecs.encode` as protocols 0-2 use it to store `bytes` (latin-1 only; no other codec is reachable)."""
    if str(encoding).lower().replace("_", "-") not in ("latin1", "latin-1", "iso-8859-1"):
        raise ForbiddenGlobal("_codecs", f"encode(encoding={encoding!r})")
    if not isinstance(obj, str):
        raise pickle.UnpicklingError(f"_codecs.encode of a {type(obj).__name__}")
    return obj.encode("latin-1", errors)


def _numpy_attr(name: str):
    """numpy's private pickle helper `name` from `numpy._core` (2.x) or `numpy.core` (1.x), without importing
    the deprecated `numpy.core` shim on numpy 2."""
    for mod in ("_core", "core"):
        sub = getattr(np, mod, None)
        for part in ("multiarray", "numeric"):
            obj = getattr(getattr(sub, part, None), name, None)
            if obj is not None:
                return obj
    return None


def _allowed() -> dict[tuple[str, str], object]:
    table: dict[tuple[str, str], object] = {}
    plain = {"dict": dict, "list": list, "tuple": tuple, "set": set, "frozenset": frozenset, "str": str,
             "bytes": bytes, "bytearray": bytearray, "int": int, "float": float, "complex": complex, "bool": bool}
    for name, obj in plain.items():
        table[("builtins", name)] = obj
        table[("__builtin__", name)] = obj
    table[("__builtin__", "long")] = int
    table[("__builtin__", "unicode")] = str
    table[("collections", "OrderedDict")] = collections.OrderedDict
    table[("collections", "defaultdict")] = collections.defaultdict
    table[("_codecs", "encode")] = _latin1_encode
    table[("numpy", "ndarray")] = np.ndarray
    table[("numpy", "dtype")] = np.dtype
    for helper, parts in (("_reconstruct", ("multiarray",)), ("scalar", ("multiarray",)),
                          ("_frombuffer", ("numeric",))):
        obj = _numpy_attr(helper)
        if obj is None:
            continue
        for pkg in ("numpy.core", "numpy._core"):
            for part in parts:
                table[(f"{pkg}.{part}", helper)] = obj
    table[("metadrive.scenario.scenario_description", "ScenarioDescription")] = dict
    return table


ALLOWED_GLOBALS = _allowed()


class SafeUnpickler(pickle.Unpickler):
    """`pickle.Unpickler` whose `find_class` returns only `ALLOWED_GLOBALS` and raises `ForbiddenGlobal` for
    anything else (the global is never imported, so nothing it would run is reached)."""

    def find_class(self, module, name):
        try:
            return ALLOWED_GLOBALS[(module, name)]
        except KeyError:
            raise ForbiddenGlobal(module, name) from None

    def persistent_load(self, pid):
        raise pickle.UnpicklingError("persistent ids are not supported")


def loads(data: bytes, path: str | os.PathLike | None = None):
    """Unpickles `data` with `SafeUnpickler`; errors are `DataError`s naming `path`."""
    return _load(io.BytesIO(data), path)


def load(path: str | os.PathLike):
    """Reads the pickle file `path` with `SafeUnpickler`.

    Raises `DataError` naming the file for an unreadable, truncated or corrupt file and for a pickle that names
    any global outside `ALLOWED_GLOBALS` (which is refused before it could run).
    """
    try:
        f = open(path, "rb")
    except OSError as e:
        raise DataError(path, f"cannot open: {e.strerror or e}") from e
    with f:
        return _load(f, path)


def _load(f, path):
    try:
        return SafeUnpickler(f).load()
    except ForbiddenGlobal as e:
        raise DataError(path, f"refused to unpickle: the pickle names the global '{e.module}.{e.name}', which is "
                              "not a plain container, scalar or numpy array (pickles can run code when loaded; "
                              "only plain dicts, lists and numpy arrays are read)") from None
    except EOFError as e:
        raise DataError(path, f"truncated pickle (the data ends early: {e or 'ran out of input'})") from None
    except pickle.UnpicklingError as e:
        msg = str(e)
        if "truncated" in msg:
            raise DataError(path, f"truncated pickle ({msg})") from None
        raise DataError(path, f"corrupt pickle: {msg}") from None
    except (ValueError, TypeError, AttributeError, IndexError, KeyError, struct.error, UnicodeDecodeError,
            MemoryError, OverflowError, RecursionError) as e:
        raise DataError(path, f"corrupt or truncated pickle: {type(e).__name__}: {e}") from None
