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


@pytest.fixture
def tiny_pair(tmp_path):
    """A tiny hopper-shaped source file and a synthetic artifact built on it."""
    from test_merge import write_source, write_synthetic

    source = write_source(tmp_path / "source.hdf5")
    write_synthetic(tmp_path / "art.hdf5", source)
    return str(source), tmp_path / "art.hdf5"
