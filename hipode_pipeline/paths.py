"""Where datasets, caches and artifacts live on disk."""

from __future__ import annotations

import os
from pathlib import Path

DATASETS_ENV_VAR = "MINARI_DATASETS_PATH"


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
    """The `stages/` folder of per-task configuration shipped beside the package."""
    return Path(__file__).resolve().parent.parent / "stages"
