"""Writing files so that a reader never sees half of one, and hashing them.

Every output goes to a temporary file in its target's folder and is renamed over the target
once complete (rename is atomic within one file system). A writer that is killed leaves at most
a hidden `.<name>.*.tmp` file behind, never a truncated target.
"""

from __future__ import annotations

import contextlib
import hashlib
import io
import json
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import torch

from hipode_pipeline.errors import DataFormatError


@contextlib.contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """Yield a temporary path beside `path`: on success it replaces `path`, on error it goes."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    handle, temp_name = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    os.close(handle)
    temp = Path(temp_name)
    # mkstemp creates the file 0600; give the final file what a plain open() would
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(temp, 0o666 & ~umask)
    try:
        yield temp
        os.replace(temp, path)
    finally:
        temp.unlink(missing_ok=True)


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
