"""Atomic writes (`atomic_path`: a temporary sibling renamed onto the path) and the removal of the
temporaries a killed writer left behind (`remove_temporaries`, `output_folder`'s staging folders too)."""

from __future__ import annotations

import contextlib
import os
import re
import shutil
import tempfile
from collections.abc import Iterator
from pathlib import Path


def _umask() -> int:
    mask = os.umask(0o022)  # the only way to read it is to set it: put it straight back
    os.umask(mask)
    return mask


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary sibling of `path`; rename it onto `path` only if the block succeeds.

    A reader never sees a half-written file: on any error the temporary is removed and `path` is
    left as it was. (A folder of outputs: `output_folder`.)
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    try:
        fd, name = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=".tmp" + "".join(path.suffixes), dir=path.parent)
        os.close(fd)
        tmp = Path(name)
    except OSError as error:   # name the file being written, not its temporary
        raise OSError(error.errno, error.strerror, os.fspath(path)) from None
    try:
        yield tmp
        # mkstemp / mkdtemp make the temporary private (0600 / 0700): give it the mode a plain open or
        # mkdir would have given `path` under the user's umask
        tmp.chmod(0o666 & ~_umask())
        os.replace(tmp, path)
    except BaseException as error:
        if isinstance(error, OSError) and (error.filename is None or os.fspath(error.filename) == os.fspath(tmp)):
            error.filename = os.fspath(path)   # a failed write() names no file, or the temporary: name the target
            error.filename2 = None
        tmp.unlink(missing_ok=True)
        raise


# `atomic_path`'s temporaries: ".NAME." + mkstemp's 8 random characters + ".tmp" + the suffixes
_TEMPORARY = re.compile(r"^\..+\.[a-z0-9_]{8}\.tmp(\..+)?$")


def remove_temporaries(directory: str | os.PathLike) -> list[Path]:
    """Remove the temporaries of `atomic_path` in `directory` (not below it): a writer killed with
    SIGKILL leaves its temporary behind. Call it only while holding the directory's `output_lock`
    (another writer's temporaries are live). Returns the removed paths."""
    directory = Path(directory)
    removed = []
    with contextlib.suppress(FileNotFoundError, NotADirectoryError):
        for entry in os.scandir(directory):
            if _TEMPORARY.match(entry.name):
                path = directory / entry.name
                if entry.is_dir(follow_symlinks=False):
                    shutil.rmtree(path, ignore_errors=True)
                else:
                    path.unlink(missing_ok=True)
                removed.append(path)
    return removed
