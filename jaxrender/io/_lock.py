"""One writer per output directory: `output_lock(DIR)` holds `DIR/.lock` while a command writes DIR.

The lock file records its owner (pid, host, start time, command line) and is held with `flock`:
the kernel (or the NFS lock manager) releases it when its process dies, however it dies, so a lock
left by a dead process is simply taken over. A second writer stops at once with `OutputBusy`
naming the owner. On a file system without `flock`, the recorded owner decides: a lock of a
process that no longer runs on this host is taken over, any other is respected. The lock file is
removed when the writer finishes; the lock is reentrant within a process (a fit that ingests and
then builds its pyramid takes it once per step).
"""

from __future__ import annotations

import contextlib
import datetime
import errno
import fcntl
import json
import os
import socket
import sys
import threading
from collections.abc import Iterator
from pathlib import Path

from ..errors import InputError, OutputBusy

__all__ = ["LOCK_NAME", "output_lock", "lock_owner"]

LOCK_NAME = ".lock"
_HELD: dict[str, list] = {}   # real path of a lock file -> [fd, depth] held by this process
_GUARD = threading.Lock()


def lock_owner(directory: str | os.PathLike) -> dict | None:
    """The owner recorded in `DIR/.lock` (pid, host, started, command) while a writer holds it, else None."""
    path = Path(directory) / LOCK_NAME
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return None
    try:
        if _try_flock(fd, shared=True) is True:   # nobody holds it: a lock file left by a dead writer
            fcntl.flock(fd, fcntl.LOCK_UN)
            return None
        return _parse(os.read(fd, 65536))
    finally:
        os.close(fd)


def describe_owner(owner: dict | None) -> str:
    if not owner:
        return "another process"
    return (f"pid {owner.get('pid')} on {owner.get('host')} since {owner.get('started')} "
            f"({owner.get('command', '?')})")


@contextlib.contextmanager
def output_lock(directory: str | os.PathLike) -> Iterator[Path]:
    """Hold `directory/.lock` (creating the directory) while the block runs; `OutputBusy` when another
    live process holds it, `InputError` when `directory` exists and is not a directory. A directory
    this call created and that is empty at the end is removed again."""
    directory = Path(directory)
    if directory.exists() and not directory.is_dir():
        raise InputError(directory, "exists and is not a directory; choose a new output path")
    created = not directory.exists()
    directory.mkdir(parents=True, exist_ok=True)
    path = directory / LOCK_NAME
    key = os.path.realpath(path)
    try:
        with _GUARD:
            held = _HELD.get(key)
            if held is not None:
                held[1] += 1
            else:
                _HELD[key] = [_acquire(path, directory), 1]
    except BaseException:
        if created:
            with contextlib.suppress(OSError):
                directory.rmdir()
        raise
    try:
        yield path
    finally:
        with _GUARD:
            held = _HELD[key]
            held[1] -= 1
            if held[1] == 0:
                del _HELD[key]
                _release(path, held[0])
        if created:
            with contextlib.suppress(OSError):
                directory.rmdir()   # only if empty: nothing was written


def _try_flock(fd: int, *, shared: bool = False) -> bool | None:
    """True: locked; False: another open file holds it; None: the file system has no flock."""
    try:
        fcntl.flock(fd, (fcntl.LOCK_SH if shared else fcntl.LOCK_EX) | fcntl.LOCK_NB)
        return True
    except OSError as error:
        if error.errno in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):
            return False
        if error.errno in (errno.ENOLCK, errno.EOPNOTSUPP, errno.ENOSYS, errno.EINVAL):
            return None
        raise


def _parse(data: bytes) -> dict | None:
    try:
        owner = json.loads(data.decode())
    except (UnicodeDecodeError, ValueError):
        return None
    return owner if isinstance(owner, dict) else None


def _alive(owner: dict | None) -> bool:
    """Whether the process that wrote `owner` may still run (another host's: assumed yes)."""
    if not owner or not isinstance(owner.get("pid"), int):
        return False
    if owner.get("host") != socket.gethostname():
        return True
    if owner["pid"] == os.getpid():
        return False
    try:
        os.kill(owner["pid"], 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def _acquire(path: Path, directory: Path) -> int:
    for _ in range(100):   # retried only when another writer replaced the file between open and lock
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            locked = _try_flock(fd)
            if locked is False or (locked is None and _alive(_parse(os.pread(fd, 65536, 0)))):
                owner = _parse(os.pread(fd, 65536, 0))
                raise OutputBusy(directory, f"{describe_owner(owner)} is writing it (lock {path}); wait for it "
                                            "to finish, or write elsewhere")
            try:
                same = os.stat(path).st_ino == os.fstat(fd).st_ino
            except FileNotFoundError:
                same = False
            if not same:   # the previous owner removed it as we opened it: take the new file
                os.close(fd)
                continue
            owner = {"pid": os.getpid(), "host": socket.gethostname(),
                     "started": datetime.datetime.now().astimezone().isoformat(timespec="seconds"),
                     "command": " ".join([Path(sys.argv[0]).name, *sys.argv[1:]]) if sys.argv else "python"}
            os.ftruncate(fd, 0)
            os.pwrite(fd, (json.dumps(owner) + "\n").encode(), 0)
            return fd
        except BaseException:
            os.close(fd)
            raise
    raise OutputBusy(directory, f"the lock {path} keeps changing hands; try again")


def _release(path: Path, fd: int) -> None:
    try:
        if os.stat(path).st_ino == os.fstat(fd).st_ino:
            path.unlink()   # while still locked: a waiting writer then finds the file gone and retries
    except OSError:
        pass   # the directory itself was removed (a failed first run), or the file system went away
    finally:
        os.close(fd)
