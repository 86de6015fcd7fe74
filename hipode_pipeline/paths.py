"""Where datasets, caches and artifacts live on disk."""

from __future__ import annotations

import os
from pathlib import Path

from hipode_pipeline.errors import InstallationError

DATASETS_ENV_VAR = "MINARI_DATASETS_PATH"
# the file whose presence marks a complete stages/ folder
STAGES_MARKER = "tasks.toml"


def datasets_root() -> Path:
    """The dataset root: $MINARI_DATASETS_PATH, else ./datasets (Minari reads the same variable)."""
    return Path(os.environ.get(DATASETS_ENV_VAR, "datasets")).expanduser().resolve()


def use_datasets_root(root: Path | None = None) -> Path:
    """Point Minari at our dataset root (it only reads the environment variable) and return it."""
    root = (root or datasets_root()).resolve()
    root.mkdir(parents=True, exist_ok=True)
    os.environ[DATASETS_ENV_VAR] = str(root)
    return root


def stages_dir() -> Path:
    """The folder of per-task configuration (tasks.toml, defaults.toml, collect.toml, train.toml).

    In a source checkout (and an editable install) it is the checkout's top-level `stages/`,
    the one place it is edited; an installed wheel carries a copy as `hipode_pipeline/stages/`.
    """
    package = Path(__file__).resolve().parent
    checkout = package.parent
    if (checkout / "pyproject.toml").is_file() and (checkout / "stages" / STAGES_MARKER).is_file():
        return checkout / "stages"
    packaged = package / "stages"
    if (packaged / STAGES_MARKER).is_file():
        return packaged
    raise InstallationError(
        f"{packaged}: expected the per-task configuration ({STAGES_MARKER} and the other "
        "stages/*.toml files), found none; reinstall hipode-pipeline "
        "(pip install --force-reinstall hipode-pipeline, or pip install -e . in a checkout)"
    )
