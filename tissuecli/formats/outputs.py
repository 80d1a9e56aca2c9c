"""What a command may write, checked before it starts: no output replaces a file unless
asked to, none is one of the command's inputs, and every one can be created.

Outputs are whole files (a parameter file, a report, a CSV, a summary: written
atomically, replaced only with ``force``) or HDF5 files that gain a group (a
session, a play log: appended to, never overwritten, so an existing file is fine).
"""

from __future__ import annotations

import os
import stat
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from ..core.errors import InputError

StrPath = str | os.PathLike[str]


@dataclass(frozen=True)
class Output:
    """One output of a command.

    Attributes
    ----------
    path : path
        Where it goes.
    option : str
        The option that names it (``--out``, ``--report``, ...), for messages.
    appends : bool
        True for HDF5 files that gain a group: an existing file is kept and added to.
    """

    path: StrPath
    option: str
    appends: bool = False


def check_outputs(
    outputs: Sequence[Output | None],
    inputs: Sequence[StrPath | None] = (),
    *,
    force: bool = False,
) -> None:
    """Refuse, before any work, outputs that would destroy a file or cannot be written.

    Parameters
    ----------
    outputs : sequence of Output or None
        The command's outputs (None: not asked for).
    inputs : sequence of path or None
        Files the command reads; no output may be one of them, through any link,
        even with ``force``.
    force : bool
        Replace whole-file outputs that exist.

    Raises
    ------
    InputError
        An output is an input or another output, exists (without ``force``), is a
        directory, or its directory is missing or not writable.
    """
    wanted = [o for o in outputs if o is not None]
    sources = [Path(p) for p in inputs if p is not None]
    for i, out in enumerate(wanted):
        path = Path(out.path)
        for src in sources:
            if _same_file(path, src):
                raise InputError(
                    f"{out.option} {path} is the input file {src}; write to another path"
                )
        for other in wanted[:i]:
            if _same_file(path, Path(other.path)):
                raise InputError(
                    f"{other.option} and {out.option} name the same file {path}; "
                    "give each its own path"
                )
        if path.is_dir():
            raise InputError(f"{out.option} {path} is a directory; give a file path")
        _refuse_special(path, out.option)
        if path.exists() or path.is_symlink():
            if not (out.appends or force):
                raise InputError(
                    f"{out.option} {path} exists; choose another path, or pass --force "
                    "to replace it"
                )
        parent = path.parent if str(path.parent) else Path(".")
        if not parent.is_dir():
            raise InputError(
                f"cannot write {out.option} {path}: directory {parent} does not exist; "
                "create it first"
            )
        if not os.access(parent, os.W_OK | os.X_OK):
            raise InputError(
                f"cannot write {out.option} {path}: directory {parent} is not writable"
            )


def check_directory_outputs(
    directory: StrPath, names: Sequence[str], option: str, *, force: bool = False
) -> None:
    """Refuse, before any work, a directory of outputs that cannot take ``names``: it
    is a file, its parent is missing or not writable, or one of the names in it exists
    (without ``force``) or is not a regular file.

    Raises
    ------
    InputError
    """
    path = Path(directory)
    if path.exists() or path.is_symlink():
        if not path.is_dir():
            raise InputError(f"{option} {path} is not a directory; give a directory path")
        if not os.access(path, os.W_OK | os.X_OK):
            raise InputError(f"cannot write {option} {path}: the directory is not writable")
        for name in names:
            inside = path / name
            _refuse_special(inside, option)
            if inside.is_dir():
                raise InputError(f"{option}: {inside} is a directory; remove it or choose another")
            if (inside.exists() or inside.is_symlink()) and not force:
                raise InputError(
                    f"{option}: {inside} exists; choose another directory, or pass --force "
                    "to replace it"
                )
        return
    parent = path.parent if str(path.parent) else Path(".")
    if not parent.is_dir():
        raise InputError(
            f"cannot write {option} {path}: directory {parent} does not exist; create it first"
        )
    if not os.access(parent, os.W_OK | os.X_OK):
        raise InputError(f"cannot write {option} {path}: directory {parent} is not writable")


_KINDS = (
    (stat.S_ISFIFO, "a named pipe (FIFO)"),
    (stat.S_ISCHR, "a character device"),
    (stat.S_ISBLK, "a block device"),
    (stat.S_ISSOCK, "a socket"),
)


def _refuse_special(path: Path, option: str) -> None:
    """Refuse an output that is neither a regular file nor a path one can be created at:
    a FIFO (writing would wait for a reader forever), a device, a socket, or a symbolic
    link to nothing (the file would appear elsewhere, where the link points)."""
    try:
        mode = path.stat().st_mode
    except FileNotFoundError:
        if path.is_symlink():
            raise InputError(
                f"{option} {path} is a symbolic link to {os.readlink(path)}, which does not "
                "exist; remove the link or give another path"
            ) from None
        return
    except OSError as exc:  # a loop of links, a permission denied on the way
        raise InputError(f"cannot write {option} {path}: {exc.strerror}") from None
    for test, kind in _KINDS:
        if test(mode):
            raise InputError(f"{option} {path} is {kind}, not a regular file; give a file path")


def _same_file(a: Path, b: Path) -> bool:
    """Whether two paths name one file: the same inode when both exist (hard and
    symbolic links included), else the same resolved path."""
    try:
        return os.path.samefile(a, b)
    except OSError:
        return os.path.realpath(a) == os.path.realpath(b)
