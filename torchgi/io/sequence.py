"""Ordered sets of frames on disk: a folder, a glob, a ``name_####.exr`` pattern, or a list."""

from __future__ import annotations

import glob
import os
import re
from collections.abc import Sequence
from pathlib import Path

__all__ = ["frame_paths"]


def _natural(path: Path) -> list:
    """Sort key: runs of digits compared as numbers (``f_9`` before ``f_10``)."""
    return [int(part) if part.isdigit() else part for part in re.split(r"(\d+)", path.name)]


def frame_paths(inputs: Sequence[str | os.PathLike]) -> list[Path]:
    """The frames of an animation, in order.

    Args:
        inputs: one folder (its ``*.exr`` files), one glob (``"render_*.exr"``), one pattern with a
            run of ``#`` for the frame number (``"render_####.exr"``: the files whose digits fill
            it), or several paths (taken in the order given, as a shell expands a glob). Folders,
            globs and patterns are sorted by frame number (digits compared as numbers).

    Returns:
        The paths, in frame order, each an existing file.

    Raises:
        FileNotFoundError: nothing matched, or a listed file does not exist (the message names it).
        ValueError: the same file twice, two frames with one file name (their outputs would
            collide), frames of another image size than the first (read from the OpenEXR headers),
            or, from a folder or a glob, files whose names differ other than in the frame number
            (``shot_0001.exr`` beside ``other_0001.exr``).

    Example:
        >>> import tempfile
        >>> d = Path(tempfile.mkdtemp())
        >>> for k in (10, 9):
        ...     _ = (d / f"f_{k}.exr").write_bytes(b"")
        >>> [p.name for p in frame_paths([str(d / "f_#.exr")])]
        ['f_9.exr', 'f_10.exr']
    """
    if not inputs:
        raise FileNotFoundError("input: expected a folder, a glob, a name_####.exr pattern or files; got none")
    if len(inputs) == 1:
        spec = str(inputs[0])
        if os.path.isdir(spec):
            paths = sorted(Path(spec).glob("*.exr"), key=_natural)
            what = f"folder {spec} holds no .exr file"
        elif "#" in os.path.basename(spec):
            head, tail = os.path.split(spec)
            parts = re.split(r"(#+)", tail)  # literal text and runs of '#', alternately
            rx = re.compile("^" + "".join(rf"\d{{{len(t)},}}" if i % 2 else re.escape(t)
                                          for i, t in enumerate(parts)) + "$")
            paths = sorted((p for p in Path(head or ".").iterdir() if rx.match(p.name)), key=_natural)
            what = f"no file matches the pattern {spec}"
        elif glob.has_magic(spec):
            paths = sorted((Path(p) for p in glob.glob(spec)), key=_natural)
            what = f"no file matches the glob {spec}"
        else:
            paths, what = [Path(spec)], ""
        if not paths:
            raise FileNotFoundError(f"input: {what}")
    else:
        paths = [Path(p) for p in inputs]
    for p in paths:
        if not p.is_file():
            raise FileNotFoundError(f"input: no such file: {p}")
    names = [p.name for p in paths]
    if len(set(names)) != len(names):
        twice = next(n for n in names if names.count(n) > 1)
        raise ValueError(f"input: two frames are named {twice} (the same file twice, or one name in two folders)")
    if len(inputs) == 1 and len(paths) > 1:  # a folder or a glob takes every file that matches: one shot's only
        _check_one_name(paths, str(inputs[0]))
    _check_one_size(paths)
    return paths


def _name_key(path: Path) -> tuple[str, str] | None:
    """A frame's name without its frame number (the last run of digits): ``("shot_", ".exr")`` for
    ``shot_0001.exr``; None for a name without digits."""
    m = re.fullmatch(r"(.*?)(\d+)(\D*)", path.name)
    return None if m is None else (m.group(1), m.group(3))


def _check_one_name(paths: list[Path], spec: str) -> None:
    """Refuse frames of a folder or glob whose names differ other than in their frame number."""
    first = _name_key(paths[0])
    for p in paths[1:]:
        key = _name_key(p)
        if key != first:
            raise ValueError(
                f"input: {spec} mixes frames named {paths[0].name} and {p.name}"
                f"{'' if key and first else ' (one has no frame number)'}: a sequence is one name with a "
                "frame number; give a name_####.exr pattern or a glob that matches one shot"
            )


def _check_one_size(paths: list[Path]) -> None:
    """Refuse frames whose OpenEXR headers give another image size than the first frame's
    (headers only; a file that is not a readable EXR is left to the reader, which names it)."""
    try:
        import OpenEXR
    except ImportError:
        return
    first = None
    for p in paths:
        try:
            exr = OpenEXR.InputFile(str(p))
        except OSError:  # not an EXR: read_exr says so when the frame is read
            continue
        window = exr.header()["dataWindow"]
        exr.close()
        size = (window.max.x - window.min.x + 1, window.max.y - window.min.y + 1)
        if first is None:
            first = (p, size)
        elif size != first[1]:
            raise ValueError(f"input: {p.name} is {size[0]}x{size[1]} but {first[0].name} is "
                             f"{first[1][0]}x{first[1][1]}: the frames of a sequence share one size")
