"""What produced an output: package versions, Python and the code's git commit.

Every dataset, artifact and run folder records this, so a result can be traced to its code.
"""

from __future__ import annotations

import platform
import subprocess
from importlib import metadata
from pathlib import Path

import hipode_pipeline

VERSIONED_PACKAGES = ("torch", "numpy", "h5py", "gymnasium", "mujoco", "minari")


def package_versions() -> dict[str, str | None]:
    """Versions of this package, its numeric stack, Python and the git commit (None if unknown)."""
    versions: dict[str, str | None] = {
        "hipode_pipeline": hipode_pipeline.__version__,
        "python": platform.python_version(),
    }
    for name in VERSIONED_PACKAGES:
        try:
            versions[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            versions[name] = None
    versions["git_commit"] = git_commit()
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
