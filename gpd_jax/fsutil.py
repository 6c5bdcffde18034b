"""File-system helpers shared by the writers of data stores, exports and evaluation outputs."""

from __future__ import annotations

import os
import shutil


def umask_mode(path: str, directory: bool = False) -> None:
    """Gives a temporary from `tempfile.mkstemp`/`mkdtemp` (private: 0600/0700) the mode a plain open/makedirs
    would have, before it is renamed into place, so that what gpd_jax writes can be read by the other users the
    umask allows."""
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(path, (0o777 if directory else 0o666) & ~umask)


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
