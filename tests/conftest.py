"""Shared fixtures: every test gets its own dataset root, so nothing touches ./datasets."""

from __future__ import annotations

import os

import pytest
import torch

# Two test workers on two cores: one torch thread each avoids oversubscription (stage one
# reads OMP_NUM_THREADS for its own thread count, subprocesses inherit it).
torch.set_num_threads(1)
os.environ["OMP_NUM_THREADS"] = "1"
os.environ.setdefault("MUJOCO_GL", "disable")


@pytest.fixture(autouse=True)
def dataset_root(tmp_path, monkeypatch):
    """Point the dataset root (and Minari) at a fresh temporary folder."""
    root = tmp_path / "datasets"
    root.mkdir()
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(root))
    return root
