"""Moving artifacts between machines: export with a sha256 sidecar, import into the dataset root.

Whatever is installed is what was checked: import copies into a temporary file beside the
target, validates that copy (schema, content checksum, and the sidecar's file hash when one
came along) and only then moves it into place. A file that fails is never left behind. Without
--force nothing is ever replaced, even by two imports (or exports) of one name at once: each
holds the target's lock, and the final step is a hard link, which fails if the name exists.
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path
from typing import Any

from hipode_pipeline.console import shorten
from hipode_pipeline.data.catalog import ARTIFACTS_DIR
from hipode_pipeline.data.load import HDF5_SUFFIXES
from hipode_pipeline.errors import DataFormatError, OverwriteError
from hipode_pipeline.files import (
    atomic_path,
    check_output_file,
    file_sha256,
    output_lock,
    write_text_atomic,
)
from hipode_pipeline.paths import datasets_root
from hipode_pipeline.validation import (
    ValidationReport,
    require_regular_file,
    validate_artifact,
)

SIDECAR_SUFFIX = ".sha256"
SIDECAR_READ_LIMIT = 4096


def sidecar_path(path: Path) -> Path:
    """`<file>.sha256`, in `sha256sum` format: `<hex>  <file name>`."""
    return path.with_name(path.name + SIDECAR_SUFFIX)


def require_valid(path: Path) -> ValidationReport:
    """Validate `path`; any error becomes a DataFormatError naming the first broken field and
    how many there are in all."""
    path = Path(path)
    require_regular_file(path)
    report = validate_artifact(path)
    if not report.valid:
        first, count = report.errors[0], len(report.errors)
        more = (
            f" ({count - 1} more violation(s); `hipode validate` lists them)" if count > 1 else ""
        )
        raise DataFormatError(path, first.field, first.expected, f"{shorten(first.found)}{more}")
    return report


def export_artifact(artifact: Path, out: Path, *, force: bool = False) -> dict[str, Any]:
    """Copy a valid artifact to `out` (atomically) and write `out.sha256` beside it."""
    artifact, out = Path(artifact), Path(out)
    _check_outputs(out)
    require_valid(artifact)
    with output_lock(out, command="hipode export"):
        _refuse_existing([out, sidecar_path(out)], force)
        digest = _copy_checked(artifact, out, expected_sha256=file_sha256(artifact), force=force)
        return {"out": str(out), **_write_sidecar(out, digest)}


def _check_outputs(out: Path) -> None:
    """--out and its sidecar must be file paths (not folders) in a folder that can exist."""
    check_output_file(out, "--out")
    check_output_file(sidecar_path(out), "--out's sidecar")


def _write_sidecar(out: Path, digest: str) -> dict[str, str]:
    """`out.sha256` in sha256sum's format, so `sha256sum -c` checks a shared copy."""
    write_text_atomic(sidecar_path(out), f"{digest}  {out.name}\n")
    return {"sha256": digest, "sidecar": str(sidecar_path(out))}


def export_d4rl(
    artifact: Path,
    source_spec: str,
    out: Path,
    *,
    root: Path | None = None,
    force: bool = False,
) -> dict[str, Any]:
    """Source ⊕ synthetic as one D4RL-format HDF5 file (hipode.merge's layout, with an
    is_synthetic mask) for CORL-style scripts, plus `out.sha256`."""
    from hipode_pipeline.merge import merge_files

    artifact, out = Path(artifact), Path(out)
    _check_outputs(out)
    require_valid(artifact)
    with output_lock(out, command="hipode export"):
        _refuse_existing([out, sidecar_path(out)], force)
        summary = merge_files(source_spec, artifact, out, root=root, force=force)
        return {**summary, **_write_sidecar(out, file_sha256(out))}


def export_minari(
    artifact: Path,
    source_spec: str,
    dataset_id: str,
    *,
    root: Path | None = None,
    force: bool = False,
) -> dict[str, Any]:
    """Source ⊕ synthetic as Minari dataset `dataset_id` under the dataset root, after the id
    and the artifact check out (hipode_pipeline.minari_export has the layout)."""
    from hipode_pipeline.merge import load_merged
    from hipode_pipeline.minari_export import check_dataset_id, write_merged_minari

    root = root or datasets_root()
    final = check_dataset_id(dataset_id, root, force)
    require_valid(Path(artifact))
    merged = load_merged(source_spec, Path(artifact), root=root)
    with output_lock(final, command="hipode export"):
        check_dataset_id(dataset_id, root, force)  # another export may have made it meanwhile
        return write_merged_minari(merged, dataset_id, root, force=force)


def import_artifact(path: Path, *, root: Path | None = None, force: bool = False) -> dict[str, Any]:
    """Validate an artifact (schema, checksum, and `path.sha256` if present) and copy it into
    `<root>/artifacts/`; an existing file there is replaced only with `force`."""
    path = Path(path)
    require_regular_file(path)
    if path.suffix.lower() not in HDF5_SUFFIXES:
        raise DataFormatError(path, "file name", f"a name ending in {' or '.join(HDF5_SUFFIXES)}")
    target = (root or datasets_root()) / ARTIFACTS_DIR / path.name
    check_output_file(target, "import target")
    expected = _sidecar_digest(path)
    with output_lock(target, command="hipode import"):
        _refuse_existing([target], force)
        with atomic_path(target, replace=force) as temp:
            shutil.copyfile(path, temp)
            digest = file_sha256(temp)
            if expected is not None and digest != expected:
                raise DataFormatError(
                    path, "file sha256", f"{expected} (from {sidecar_path(path).name})", digest
                )
            # the copy is what gets installed, so the copy is what is validated
            try:
                report = require_valid(temp)
            except DataFormatError as error:
                # name the user's file, not the hidden copy
                raise DataFormatError(path, error.field, error.expected, error.found) from None
    return {
        "imported": str(target),
        "sha256": digest,
        "sidecar_checked": expected is not None,
        "schema": report.schema,
        "warnings": [v.to_dict() for v in report.violations],
    }


def _sidecar_digest(path: Path) -> str | None:
    sidecar = sidecar_path(path)
    if not sidecar.is_file():
        return None
    with open(sidecar, "rb") as f:
        # a sidecar is one line; a huge file under that name is not read whole
        words = f.read(SIDECAR_READ_LIMIT).decode(errors="replace").split()
    digest = words[0].lower() if words else ""
    if len(digest) != 64 or any(c not in "0123456789abcdef" for c in digest):
        raise DataFormatError(sidecar, "sha256", "64 hex digits, then the file name", repr(digest))
    return digest


def _copy_checked(source: Path, out: Path, *, expected_sha256: str, force: bool) -> str:
    with atomic_path(out, replace=force) as temp:
        shutil.copyfile(source, temp)
        digest = file_sha256(temp)
        if digest != expected_sha256:
            raise DataFormatError(source, "file sha256", expected_sha256, f"{digest} after copying")
    return digest


def _refuse_existing(paths: list[Path], force: bool) -> None:
    for path in paths:
        if os.path.lexists(path) and not force:
            raise OverwriteError(f"{path} already exists; pass --force to replace it")
