"""File-system helpers shared by the writers of data stores, exports and evaluation outputs."""

from __future__ import annotations

import os


def umask_mode(path: str, directory: bool = False) -> None:
    """Gives a temporary from `tempfile.mkstemp`/`mkdtemp` (private: 0600/0700) the mode a plain open/makedirs
    would have, before it is renamed into place, so that what gpd_jax writes can be read by the other users the
    umask allows."""
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(path, (0o777 if directory else 0o666) & ~umask)
