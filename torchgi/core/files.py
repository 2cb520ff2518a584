"""Files written atomically: a temporary file beside the destination, renamed over it."""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

__all__ = ["temp_beside"]


def temp_beside(path: str | os.PathLike) -> str:
    """A new empty temporary file in ``path``'s folder, for a write renamed onto ``path`` once
    complete, with the permissions ``open(path, "w")`` would give (0o666 less the umask;
    :func:`tempfile.mkstemp`'s own are 0o600, which every file renamed from it would keep).

    Example:
        >>> d = tempfile.mkdtemp()
        >>> tmp = temp_beside(os.path.join(d, "a.exr"))
        >>> os.path.dirname(tmp) == d and os.path.getsize(tmp) == 0
        True
    """
    path = Path(path)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    os.close(fd)
    mask = os.umask(0)  # read the umask (only os.umask says it): set and restore at once
    os.umask(mask)
    os.chmod(tmp, 0o666 & ~mask)
    return tmp
