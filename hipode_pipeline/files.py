"""Writing files so that a reader never sees half of one, and hashing them.

Every output goes to a temporary file in its target's folder and is renamed over the target
once complete (rename is atomic within one file system), or, where an existing file must never
be replaced, hard-linked to the target name (which fails if the name exists). A writer that is
killed leaves at most a hidden `.<name>.p<pid>@<host>.*.tmp` file behind, never a truncated
target; the next write into that folder removes it. `output_lock` keeps two processes from
building the same output at once.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import hashlib
import io
import json
import os
import re
import socket
import stat
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import torch

from hipode_pipeline.errors import DataFormatError, OverwriteError, SettingError

# a temp file's name records its writer, so a later writer can tell a dead one's leftovers
TEMP_NAME = re.compile(r"\.(?P<stem>.*)\.p(?P<pid>\d+)@(?P<host>[\w-]*)\.[^.]+\.tmp")
# a temp name keeps this much of the target's name, so it stays under NAME_MAX (255 bytes)
TEMP_STEM_LIMIT = 120
# link(2) fails with these where the file system has no hard links (FAT, some FUSE mounts)
NO_HARD_LINKS = {errno.EPERM, errno.ENOTSUP, errno.EOPNOTSUPP, errno.EMLINK, errno.ENOSYS}
# a waiter reads the lock holder's "<pid> <command>" record at most this many times, 10 ms apart
HOLDER_RECORD_POLLS = 50


def _host() -> str:
    return re.sub(r"[^\w-]", "_", socket.gethostname())[:32]


@contextlib.contextmanager
def atomic_path(path: str | Path, *, replace: bool = True) -> Iterator[Path]:
    """Yield a temporary path beside `path`: on success it becomes `path`, on error it goes.

    With `replace=False` an existing `path` is never replaced, even by a writer that got there
    first meanwhile: the temporary file is hard-linked to `path`, which fails if it exists
    (OverwriteError)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    # killed writers' leftovers go on the next write here (by dead pid: live writers are safe)
    remove_stale_temps(path.parent)
    prefix = f".{path.name[:TEMP_STEM_LIMIT]}.p{os.getpid()}@{_host()}."
    handle, temp_name = tempfile.mkstemp(prefix=prefix, suffix=".tmp", dir=path.parent)
    os.close(handle)
    temp = Path(temp_name)
    # mkstemp creates the file 0600; give the final file what a plain open() would
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(temp, 0o666 & ~umask)
    try:
        yield temp
        if replace:
            os.replace(temp, path)
        else:
            _create_from(temp, path)
    finally:
        temp.unlink(missing_ok=True)


def _create_from(temp: Path, path: Path) -> None:
    """Give `temp` the name `path` unless something already has that name."""
    try:
        os.link(temp, path)
    except FileExistsError:
        raise OverwriteError(f"{path} already exists; pass --force to replace it") from None
    except OSError as error:
        if error.errno not in NO_HARD_LINKS:
            raise
        # no hard links here: check, then rename (callers hold output_lock, so no hipode
        # writer can slip in between)
        if os.path.lexists(path):
            raise OverwriteError(f"{path} already exists; pass --force to replace it") from None
        os.replace(temp, path)


def remove_stale_temps(folder: Path) -> list[Path]:
    """Remove the temp files in `folder` whose writer process is gone, and return them.

    Stale means: written on this host (the name says so) by a process id that no longer
    exists. A live writer's file is never touched, so two writers into one folder are safe;
    a reused process id only keeps a leftover longer."""
    removed = []
    host = _host()
    try:
        names = [entry.name for entry in os.scandir(folder) if entry.name.endswith(".tmp")]
    except OSError:
        return removed
    for name in names:
        match = TEMP_NAME.fullmatch(name)
        if match is None or match["host"] != host or _process_alive(int(match["pid"])):
            continue
        with contextlib.suppress(FileNotFoundError):
            (folder / name).unlink()
            removed.append(folder / name)
    return removed


def _process_alive(pid: int) -> bool:
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except (PermissionError, OverflowError):
        return pid > 0  # another user's process (or a number no process can have)
    return True


def lock_path(path: str | Path) -> Path:
    """The lock file of an output: `<folder>/.<name>.lock`."""
    path = Path(path)
    return path.with_name(f".{path.name[:TEMP_STEM_LIMIT]}.lock")


@contextlib.contextmanager
def output_lock(path: str | Path, *, command: str) -> Iterator[bool]:
    """Hold an exclusive lock on output `path` (flock on `lock_path(path)`); yield whether it
    had to wait for another process.

    A second process that wants the same output says on stderr that it waits, then waits:
    when it gets the lock the output is complete, so it usually finds it up to date. The lock
    file records `<pid> <command>` for that message and is removed on release."""
    path = Path(path)
    lock = lock_path(path)
    # folders made only for the lock go again if the command writes nothing into them
    made = [folder for folder in [lock.parent, *lock.parent.parents] if not folder.exists()]
    fd, waited = _acquire(lock, path)
    try:
        if fd is not None:
            os.ftruncate(fd, 0)
            os.pwrite(fd, f"{os.getpid()} {command}\n".encode(), 0)
        yield waited
    finally:
        if fd is not None:
            lock.unlink(missing_ok=True)
            os.close(fd)
        for folder in made:
            with contextlib.suppress(OSError):  # not empty: something was written there
                folder.rmdir()


def _acquire(lock: Path, path: Path) -> tuple[int | None, bool]:
    """(descriptor holding the lock, whether we waited); None where locks are unsupported."""
    waited = False
    while True:
        lock.parent.mkdir(parents=True, exist_ok=True)
        try:
            fd = os.open(lock, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o666)
        except FileNotFoundError:
            if lock.parent.is_dir():
                # the folder is there (the lock may be a dangling link): nothing to wait for
                raise OverwriteError(
                    f"{path}: expected a writable output place, found none for its lock {lock}"
                ) from None
            continue  # another process removed the folder it had made for its own lock
        try:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                if not waited:
                    _say_waiting(fd, path)
                waited = True
                fcntl.flock(fd, fcntl.LOCK_EX)
        except OSError as error:
            os.close(fd)
            if error.errno in (errno.ENOLCK, errno.ENOTSUP, errno.EOPNOTSUPP):
                # no locks on this file system: go on unlocked (atomic_path still never leaves
                # a partial file, and replace=False still never replaces one)
                return None, waited
            raise
        except BaseException:  # Ctrl-C while waiting
            os.close(fd)
            raise
        # the holder before us removes the file on release: a lock on a removed file is none
        with contextlib.suppress(FileNotFoundError):
            if os.path.samestat(os.fstat(fd), os.stat(lock)):
                return fd, waited
        os.close(fd)


def _say_waiting(fd: int, path: Path) -> None:
    from hipode_pipeline import console

    # the holder writes its record just after it takes the lock: give it that moment
    for _ in range(HOLDER_RECORD_POLLS):
        record = os.pread(fd, 200, 0).decode(errors="replace")
        if record.endswith("\n"):
            break
        time.sleep(0.01)
    words = record.split(maxsplit=1)
    pid = words[0] if words and words[0].isdigit() else "?"
    command = words[1].strip() if len(words) > 1 else "hipode"
    console.err.print(console.plain(f"waiting for another `{command}` writing {path} (pid {pid})…"))


def display_path(path: str | Path | None) -> str | None:
    """A path as records show it: relative to the working directory when inside it, so run
    records and reports written in a checkout name no folder of the machine."""
    if path is None:
        return None
    if not Path(path).is_absolute():
        return str(path)  # already relative (or a dataset id such as local/hopper/...)
    resolved, here = Path(path).resolve(), Path.cwd().resolve()
    return str(resolved.relative_to(here)) if resolved.is_relative_to(here) else str(path)


def path_kind(path: str | Path) -> str:
    """What is at `path`, in words, for an error message. Only stat is called: a FIFO is never
    opened, so it cannot block."""
    try:
        mode = os.stat(path).st_mode
    except FileNotFoundError:
        return "a symlink to nothing (dangling)" if os.path.islink(path) else "nothing"
    except OSError as error:
        if error.errno == errno.ELOOP:
            return "a symlink loop"
        if error.errno == errno.ENOTDIR:
            return "nothing (a parent is not a folder)"
        return f"unreadable ({error.strerror})"
    if stat.S_ISREG(mode):
        return "a file"
    if stat.S_ISDIR(mode):
        return "a directory"
    if stat.S_ISFIFO(mode):
        return "a FIFO (named pipe)"
    if stat.S_ISSOCK(mode):
        return "a socket"
    return "a device" if stat.S_ISCHR(mode) or stat.S_ISBLK(mode) else "a special file"


def check_output_file(path: str | Path, option: str | None = None) -> Path:
    """An output file path: a regular file or nothing, in a folder that exists or can be made.

    `option` (e.g. "--out") names where the path came from in the error message."""
    path = Path(path)
    label = f"{option} {path}" if option else str(path)
    if os.path.lexists(path) and path_kind(path) not in (
        "a file",
        "a symlink to nothing (dangling)",
    ):
        raise SettingError(f"{label}: expected a file path, found {path_kind(path)}")
    _check_parents(path, label)
    return path


def check_output_folder(path: str | Path, option: str | None = None) -> Path:
    """An output folder: an existing folder, or nothing in a folder that can hold one."""
    path = Path(path)
    label = f"{option} {path}" if option else str(path)
    if os.path.lexists(path) and path_kind(path) != "a directory":
        raise SettingError(f"{label}: expected a folder, found {path_kind(path)}")
    _check_parents(path, label)
    return path


def _check_parents(path: Path, label: str) -> None:
    for parent in path.parents:
        if parent.is_dir():
            return
        if os.path.lexists(parent):
            raise SettingError(f"{label}: expected a folder at {parent}, found {path_kind(parent)}")


def write_bytes_atomic(path: str | Path, data: bytes | memoryview) -> None:
    with atomic_path(path) as temp:
        temp.write_bytes(data)


def write_text_atomic(path: str | Path, text: str) -> None:
    with atomic_path(path) as temp:
        temp.write_text(text)


def write_json_atomic(path: str | Path, data: Any) -> None:
    """Indented, key-sorted JSON; values JSON cannot hold (paths, numpy scalars) become strings."""
    write_text_atomic(path, json.dumps(data, indent=2, sort_keys=True, default=str) + "\n")


def save_torch_atomic(path: str | Path, obj: Any) -> None:
    """torch.save through memory: the bytes do not depend on the file name (torch.save names the
    archive's root folder after the file), so equal tensors give equal file checksums."""
    buffer = io.BytesIO()
    torch.save(obj, buffer)
    write_bytes_atomic(path, buffer.getbuffer())


def save_npz_atomic(path: str | Path, arrays: dict[str, np.ndarray]) -> None:
    buffer = io.BytesIO()
    np.savez(buffer, **arrays)
    write_bytes_atomic(path, buffer.getbuffer())


def save_figure_atomic(figure: Any, path: str | Path) -> None:
    """Write a matplotlib figure as PNG atomically, and free it."""
    import matplotlib.pyplot as plt

    figure.tight_layout()
    try:
        with atomic_path(path) as temp:
            figure.savefig(temp, format="png")
    finally:
        plt.close(figure)


def file_sha256(path: str | Path) -> str:
    """sha256 of a file's bytes, read in blocks."""
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 22), b""):
            digest.update(block)
    return digest.hexdigest()


def load_torch(path: str | Path, what: str) -> Any:
    """torch.load restricted to tensors and plain containers (never unpickles code); a truncated or
    foreign file is a DataFormatError saying what was expected."""
    try:
        return torch.load(path, map_location="cpu", weights_only=True)
    except Exception as error:  # torch raises several types for truncated or foreign files
        raise DataFormatError(
            path, "(file)", f"{what} readable by torch.load(weights_only=True)", error
        ) from None
