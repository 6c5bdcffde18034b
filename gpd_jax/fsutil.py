"""File-system helpers shared by the writers of data stores, exports and evaluation outputs."""

from __future__ import annotations

import contextlib
import os
import shutil
import tempfile
from collections.abc import Iterator


def umask_mode(path: str, directory: bool = False) -> None:
    """Gives a temporary from `tempfile.mkstemp`/`mkdtemp` (private: 0600/0700) the mode a plain open/makedirs
    would have, before it is renamed into place, so that what gpd_jax writes can be read by the other users the
    umask allows."""
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(path, (0o777 if directory else 0o666) & ~umask)


@contextlib.contextmanager
def atomic_directory(out_dir: str) -> Iterator[str]:
    """Yields a fresh temporary directory beside `out_dir` to write an export into; on success it becomes
    `out_dir` (`swap_in_directory`: files of an existing `out_dir` the export does not write are kept), on an
    exception it is removed and `out_dir` is untouched."""
    out_dir = os.path.abspath(out_dir)
    parent = os.path.dirname(out_dir)
    os.makedirs(parent, exist_ok=True)
    tmp = tempfile.mkdtemp(prefix=".export-", dir=parent)
    umask_mode(tmp, directory=True)  # mkdtemp makes it private; an export is meant to be shared
    try:
        yield tmp
        swap_in_directory(tmp, out_dir)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


def swap_in_directory(tmp: str, out_dir: str) -> None:
    """Moves the freshly written directory `tmp` to `out_dir` in one rename, so readers see either the old
    export or the new one, never a mixture of their files.

    Entries of an existing `out_dir` that `tmp` does not contain (a README, evaluation files, pictures written
    beside an export) are copied into `tmp` first and so survive; the ones `tmp` writes are replaced.
    `tmp` must be on the same file system as `out_dir` (make it in the same parent directory).
    """
    if not os.path.exists(out_dir):
        os.replace(tmp, out_dir)
        return
    for name in os.listdir(out_dir):
        src, dst = os.path.join(out_dir, name), os.path.join(tmp, name)
        if os.path.lexists(dst):
            continue
        if os.path.isdir(src) and not os.path.islink(src):
            shutil.copytree(src, dst, symlinks=True)
        else:
            shutil.copy2(src, dst, follow_symlinks=False)
    old = out_dir + ".old"
    shutil.rmtree(old, ignore_errors=True)
    os.replace(out_dir, old)
    os.replace(tmp, out_dir)
    shutil.rmtree(old, ignore_errors=True)
