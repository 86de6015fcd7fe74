"""Torch's thread count is set for a scope and restored: collection no longer leaves one thread."""

from __future__ import annotations

import os

import pytest
import torch

from hipode_pipeline.data import collect as collect_module
from hipode_pipeline.errors import SettingError
from hipode_pipeline.tasks import get_task
from hipode_pipeline.threads import STAGE_ONE_THREADS, stage_one_threads, torch_threads


@pytest.fixture
def two_threads():
    """Start from two torch threads (conftest sets one), so a leaked 1 shows; restore after."""
    before = torch.get_num_threads()
    torch.set_num_threads(2)
    yield
    torch.set_num_threads(before)


def test_torch_threads_sets_the_count_inside_and_restores_it(two_threads):
    with torch_threads(1) as inside:
        assert inside == torch.get_num_threads() == 1
    assert torch.get_num_threads() == 2
    with pytest.raises(RuntimeError, match="boom"), torch_threads(1):
        raise RuntimeError("boom")
    assert torch.get_num_threads() == 2
    with torch_threads(None) as inside:
        assert inside == torch.get_num_threads() == 2


@pytest.mark.parametrize("bad", [0, -1, 1.5, True])
def test_torch_threads_refuses_a_count_that_is_not_a_positive_integer(bad, two_threads):
    with pytest.raises(SettingError, match="expected a positive integer"), torch_threads(bad):
        pass
    assert torch.get_num_threads() == 2


def test_collection_runs_on_one_thread_and_gives_the_count_back(
    two_threads, dataset_root, monkeypatch
):
    seen = []

    collected = collect_module.CollectResult(dataset_ids=["fake"], seconds=0.0, policy_returns={})

    def fake_collect_in(*args, **kwargs):
        # stands in for PPO training, evaluation and rollouts
        seen.append(torch.get_num_threads())
        return collected

    monkeypatch.setattr(collect_module, "_collect_in", fake_collect_in)
    assert collect_module.collect(get_task("hopper-m-r"), root=dataset_root) is collected
    assert seen == [1]
    assert torch.get_num_threads() == 2


def test_stage_one_threads_keeps_the_users_choice(monkeypatch):
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    for phase in ("train", "generate"):
        expected = max(1, min(STAGE_ONE_THREADS[phase], os.cpu_count() or 1))
        assert stage_one_threads(phase) == expected
    monkeypatch.setenv("OMP_NUM_THREADS", "3")
    # generation keeps the user's count; training's is fixed (its weights depend on it)
    assert stage_one_threads("generate") == 3
    assert stage_one_threads("train") == STAGE_ONE_THREADS["train"]
    for bad in ("0", "two", "-2"):
        monkeypatch.setenv("OMP_NUM_THREADS", bad)
        with pytest.raises(SettingError, match="OMP_NUM_THREADS: expected a positive integer"):
            stage_one_threads("generate")
