"""What a command may do to its outputs: write the files it names, each complete, and nothing else.

    out = output_file(args.out, suffixes=(".exr", ".png"), inputs=[args.scene])  # checked before any work
    with output_folder(args.out) as stage:        # a folder output: build it in `stage` ...
        write_png(stage / "frame_000.png", image)  # ... moved into `args.out` file by file at the end

An existing output folder is used, never replaced: its other files stay, and a file of the same
name is replaced by a rename (a reader sees the old file or the new one). Nothing is removed that
the command did not write, also when it fails: then the output folder is as it was. Values that
are not finite are never written (`check_finite`): an image of NaN is a bug, not a result.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import tempfile
from collections.abc import Iterable, Iterator, Sequence
from pathlib import Path

import numpy as np

from ..errors import InputError, NonFiniteOutput

__all__ = ["output_file", "output_folder", "check_finite"]


def _same_file(a: Path, b: Path) -> bool:
    try:
        return a.exists() and b.exists() and os.path.samefile(a, b)
    except OSError:
        return False


def output_file(path: str | os.PathLike, *, suffixes: Sequence[str] = (),
                inputs: Iterable[str | os.PathLike | None] = (), make_folder: bool = False) -> Path:
    """`path` checked as a file the command will write (`InputError` otherwise), before any work:
    one of `suffixes` (when given), not an existing folder, in a folder that exists (unless
    `make_folder`: the writer makes it), and none of the command's `inputs` (a command never
    overwrites what it reads)."""
    path = Path(path)
    if suffixes and path.suffix.lower() not in suffixes:
        raise InputError(path, f"output must end in {' or '.join(suffixes)}")
    if path.is_dir():
        raise InputError(path, "is a folder; give a file name to write")
    if not make_folder and not path.parent.is_dir():
        raise InputError(path, f"the output's folder {os.fspath(path.parent)!r} does not exist")
    for source in inputs:
        if source is not None and _same_file(path, Path(source)):
            raise InputError(path, f"is an input of this command ({os.fspath(source)}); write the output elsewhere")
    return path


def _entries(folder: Path) -> Iterator[Path]:
    """Every file below `folder` (links as files), relative to it."""
    for root, dirs, files in os.walk(folder):
        for name in files + [d for d in dirs if (Path(root) / d).is_symlink()]:
            yield (Path(root) / name).relative_to(folder)


def _conflicts(stage: Path, target: Path) -> list[str]:
    """Staged files whose place in `target` is taken by a folder, or whose folder is a file there."""
    problems = []
    for relative in _entries(stage):
        place = target / relative
        if place.is_dir() and not place.is_symlink():
            problems.append(f"{os.fspath(place)}: is a folder where the command writes a file")
        for parent in list(relative.parents)[:-1]:
            if (target / parent).exists() and not (target / parent).is_dir():
                problems.append(f"{os.fspath(target / parent)}: is a file where the command writes a folder")
    return problems


@contextlib.contextmanager
def output_folder(path: str | os.PathLike, *, inputs: Iterable[str | os.PathLike | None] = ()) -> Iterator[Path]:
    """Yield a staging folder inside `path` (created if missing); when the block succeeds, move
    every file staged there into `path`, each by one rename (folders merged, other files of
    `path` kept). On any error the staging folder goes, and `path` too if this call created it,
    so the output is as it was. `inputs` that lie in `path` cannot be overwritten: a staged file of
    the same name is refused before anything moves."""
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise InputError(path, "exists and is not a folder")
    created = []
    for folder in reversed([path, *path.parents]):  # the folders this call makes, outermost first
        if not folder.exists():
            created.append(folder)
    path.mkdir(parents=True, exist_ok=True)
    try:
        stage = Path(tempfile.mkdtemp(prefix=".staging.", suffix=".tmp", dir=path))
    except OSError as error:
        _remove_empty(created)
        raise OSError(error.errno, error.strerror, os.fspath(path)) from None
    try:
        yield stage
        problems = _conflicts(stage, path)
        protected = [Path(p) for p in inputs if p is not None]
        for relative in _entries(stage):
            if any(_same_file(path / relative, p) for p in protected):
                problems.append(f"{os.fspath(path / relative)}: is an input of this command; write the output "
                                "elsewhere")
        if problems:
            raise InputError(None, "; ".join(problems))
        _move(stage, path)
        shutil.rmtree(stage)   # empty folders left by the moves: this call's own
    except BaseException:
        shutil.rmtree(stage, ignore_errors=True)
        _remove_empty(created)
        raise


def _move(stage: Path, target: Path) -> None:
    """Merge `stage` into `target`: a folder that `target` lacks moves whole, files replace files."""
    for entry in sorted(os.scandir(stage), key=lambda e: e.name):
        source, place = Path(entry.path), target / entry.name
        if entry.is_dir(follow_symlinks=False) and place.is_dir() and not place.is_symlink():
            _move(source, place)
            continue
        os.replace(source, place)


def _remove_empty(folders: list[Path]) -> None:
    for folder in reversed(folders):   # innermost first; a folder someone filled meanwhile stays
        with contextlib.suppress(OSError):
            folder.rmdir()


def check_finite(values, path: str | os.PathLike) -> None:
    """Refuse to write `values` to `path` unless every one is finite (`NonFiniteOutput`, a bug)."""
    array = np.asarray(values)
    if np.issubdtype(array.dtype, np.floating) or np.issubdtype(array.dtype, np.complexfloating):
        bad = int(array.size - np.count_nonzero(np.isfinite(array)))
        if bad:
            raise NonFiniteOutput(path, f"{bad} of {array.size} values to write are NaN or infinite; nothing "
                                        "written")
