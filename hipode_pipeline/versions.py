"""What produced an output: package versions, Python, the CPU and the code's git commit.

Every dataset, artifact and run folder records this, so a result can be traced to its code.
"""

from __future__ import annotations

import functools
import hashlib
import platform
import subprocess
from importlib import metadata
from pathlib import Path

import hipode_pipeline
from hipode_pipeline.machine import cpu_name

VERSIONED_PACKAGES = ("torch", "numpy", "h5py", "gymnasium", "mujoco", "minari")
PACKAGE_DIR = Path(hipode_pipeline.__file__).resolve().parent
# the source files whose code determines trained generators (package-relative; folders whole)
GENERATOR_CODE = ("models", "data/normalizer.py", "seeding.py")
# ... and those that determine an artifact's rows beyond its generators (Algorithm 1 and the
# termination rules; the driver and the file writer only move the rows)
ARTIFACT_CODE = (*GENERATOR_CODE, "generate.py", "envs.py")
# ... and those of the plain model-rollout baseline's rows (its behaviour model and rollouts)
ROLLOUT_CODE = (*ARTIFACT_CODE, "rollouts.py")


def package_versions(extra: tuple[str, ...] = ()) -> dict[str, str | bool | None]:
    """Versions of this package, its numeric stack (and the `extra` packages an output also
    depends on), Python, the CPU (the same seed can give other floats on another one), the git
    commit and whether the package's files differ from it (None if unknown)."""
    versions: dict[str, str | bool | None] = {
        "hipode_pipeline": hipode_pipeline.__version__,
        "python": platform.python_version(),
        "cpu": cpu_name(),
    }
    for name in (*VERSIONED_PACKAGES, *extra):
        try:
            versions[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            versions[name] = None
    versions["git_commit"] = git_commit()
    versions["git_modified"] = git_modified()
    return versions


def git_commit() -> str | None:
    """HEAD of the checkout the package runs from; None outside a git checkout."""
    try:
        done = subprocess.run(
            ["git", "rev-parse", "HEAD"],
            cwd=Path(hipode_pipeline.__file__).resolve().parent,
            capture_output=True,
            text=True,
            timeout=5,
            check=False,
        )
    except (OSError, subprocess.SubprocessError):
        return None
    return done.stdout.strip() or None if done.returncode == 0 else None


def git_modified() -> bool | None:
    """Whether the package's files in the checkout differ from HEAD (edited, added or removed,
    untracked files included), so that the commit alone does not say what ran; None outside a
    git checkout."""
    try:
        done = subprocess.run(
            ["git", "status", "--porcelain", "--untracked-files=normal", "--", "."],
            cwd=PACKAGE_DIR,
            capture_output=True,
            text=True,
            timeout=5,
            check=False,
        )
    except (OSError, subprocess.SubprocessError):
        return None
    return bool(done.stdout.strip()) if done.returncode == 0 else None


def code_digest(parts: tuple[str, ...]) -> str:
    """sha256 over the bytes of the package's .py files under `parts` (relative paths and
    contents): caches keyed on it are rebuilt when that code changes, and only then."""
    return _code_digest(PACKAGE_DIR, tuple(parts))


@functools.cache
def _code_digest(package_dir: Path, parts: tuple[str, ...]) -> str:
    digest = hashlib.sha256()
    files: set[Path] = set()
    for part in parts:
        path = package_dir / part
        files.update(path.rglob("*.py") if path.is_dir() else [path])
    for path in sorted(files):
        digest.update(path.relative_to(package_dir).as_posix().encode() + b"\0")
        # line endings are the checkout's, not the code's
        digest.update(path.read_bytes().replace(b"\r\n", b"\n") + b"\0")
    return digest.hexdigest()
