"""Write collected transitions as an ordinary Minari dataset, atomically.

Minari builds a dataset in place; we build it in a staging root beside the final one and move
the finished folder into place, so an interrupted write never leaves a half dataset behind.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import warnings
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np

from hipode_pipeline.data.ppo import RolloutBlock
from hipode_pipeline.errors import OverwriteError
from hipode_pipeline.paths import DATASETS_ENV_VAR


def episode_spans(block: RolloutBlock) -> list[tuple[int, int, int]]:
    """(env, start step, end step) of each episode of a (step, env) block, env by env, in the
    order split_episodes returns them; the last one of each env ends with the block."""
    ends_flags = block.terminations | block.truncations
    spans = []
    for env in range(block.rewards.shape[1]):
        ends = np.flatnonzero(
            ends_flags[:, env] | (np.arange(len(ends_flags)) == len(ends_flags) - 1)
        )
        starts = np.concatenate([[0], ends[:-1] + 1])
        spans += [(env, int(a), int(b)) for a, b in zip(starts, ends + 1, strict=True)]
    return spans


def split_episodes(block: RolloutBlock) -> list[dict[str, np.ndarray]]:
    """Cut each env's stream of a (step, env) block into Minari episodes.

    An episode still running at the end of the block is cut there and marked truncated, the
    same flag a time limit sets: its last state is not terminal.
    """
    truncations = block.truncations.copy()
    truncations[-1] |= ~(block.terminations | block.truncations)[-1]
    episodes = []
    for env, start, end in episode_spans(block):
        episodes.append(
            {
                "observations": np.concatenate(
                    [
                        block.observations[start:end, env],
                        block.next_observations[end - 1 : end, env],
                    ]
                ),
                "actions": block.actions[start:end, env],
                "rewards": block.rewards[start:end, env],
                "terminations": block.terminations[start:end, env],
                "truncations": truncations[start:end, env],
            }
        )
    return episodes


@contextlib.contextmanager
def _minari_root(root: Path) -> Iterator[None]:
    """Point Minari (which only reads the environment variable) at `root` for a while."""
    previous = os.environ.get(DATASETS_ENV_VAR)
    os.environ[DATASETS_ENV_VAR] = str(root)
    try:
        yield
    finally:
        if previous is None:
            os.environ.pop(DATASETS_ENV_VAR, None)
        else:
            os.environ[DATASETS_ENV_VAR] = previous


def dataset_dir(root: Path, dataset_id: str) -> Path:
    return root.joinpath(*dataset_id.split("/"))


def write_minari_dataset(
    dataset_id: str,
    episodes: list[dict[str, np.ndarray]],
    *,
    env_id: str,
    root: Path,
    staging: Path,
    ref_min_score: float,
    ref_max_score: float,
    algorithm_name: str,
    description: str,
    extra_metadata: dict[str, Any],
    force: bool = False,
    finish: Callable[[Any], None] | None = None,
    data_format: str = "hdf5",
) -> Path:
    """Create `dataset_id` under `root` from episode dicts, with `extra_metadata` added.

    An episode dict may hold `infos`, per-step info arrays (length T + 1, Minari's rule);
    `finish` gets the staged MinariDataset to add to before it is moved into place."""
    import minari
    from minari.data_collector import EpisodeBuffer
    from minari.namespace import create_namespace, list_local_namespaces

    final = dataset_dir(root, dataset_id)
    if final.exists() and not force:
        raise OverwriteError(
            f"{final}: dataset '{dataset_id}' already exists; pass --force to rebuild it"
        )
    shutil.rmtree(staging, ignore_errors=True)
    staging.mkdir(parents=True)
    buffers = [
        EpisodeBuffer(
            id=i,
            observations=e["observations"],
            actions=e["actions"],
            rewards=e["rewards"],
            terminations=e["terminations"],
            truncations=e["truncations"],
            infos=e.get("infos", {}),
        )
        for i, e in enumerate(episodes)
    ]
    with _minari_root(staging), warnings.catch_warnings():
        # Minari asks for author, e-mail and a code link; the metadata records versions instead
        warnings.filterwarnings("ignore", category=UserWarning, module="minari")
        dataset = minari.create_dataset_from_buffers(
            dataset_id,
            buffers,
            env=env_id,
            eval_env=env_id,
            algorithm_name=algorithm_name,
            ref_min_score=ref_min_score,
            ref_max_score=ref_max_score,
            description=description,
            data_format=data_format,
        )
        dataset.storage.update_metadata(extra_metadata)
        if finish is not None:
            finish(dataset)
    namespace = dataset_id.rsplit("/", 1)[0]
    with _minari_root(root):
        if namespace not in list_local_namespaces():
            create_namespace(namespace)
    if final.exists():
        # force: move the old dataset aside first so the rename below cannot fail half-way
        trash = staging.with_name(staging.name + "-old")
        shutil.rmtree(trash, ignore_errors=True)
        os.replace(final, trash)
        shutil.rmtree(trash)
    final.parent.mkdir(parents=True, exist_ok=True)
    os.replace(dataset_dir(staging, dataset_id), final)
    shutil.rmtree(staging, ignore_errors=True)
    return final
