"""Writing a whole file so that a crash never leaves half of it: a temporary file in the
same directory, then one rename over the target."""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

from ..core.errors import InputError


def write_text_atomic(path: str | os.PathLike[str], text: str) -> None:
    """Write ``text`` (UTF-8) to ``path`` through a fresh temporary file and ``os.replace``.

    The temporary name is unpredictable and created exclusively, so a planted
    symlink cannot redirect the write; a failure removes it. A rewritten file keeps
    its permissions.

    Raises
    ------
    InputError
        If the directory is missing or not writable, or the disk is full.
    """
    path = Path(path)
    try:
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    except OSError as exc:
        raise InputError(f"cannot write {path}: {exc.strerror}") from None
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as fh:
            fh.write(text)
        os.chmod(tmp, _mode_for(path))
        os.replace(tmp, path)
    except OSError as exc:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        raise InputError(f"cannot write {path}: {exc.strerror}") from None


def _mode_for(path: Path) -> int:
    """The permissions a rewrite keeps (the file's own), or a new file gets (0666 less umask)."""
    try:
        return path.stat().st_mode & 0o7777
    except OSError:
        umask = os.umask(0)
        os.umask(umask)
        return 0o666 & ~umask
