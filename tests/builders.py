"""Small, seeded test datasets: Minari episodes, local Minari datasets and D4RL-format files.

Every builder returns the ground truth it wrote, so a test can compare a loader's output with
what went in. Minari datasets are written under $MINARI_DATASETS_PATH (the autouse fixture in
conftest.py points it at a temporary folder) without building an environment.
"""

from __future__ import annotations

import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import gymnasium as gym
import h5py
import minari
import numpy as np
from gymnasium.envs.registration import EnvSpec
from minari.data_collector import EpisodeBuffer

EPISODE_FIELDS = ("observations", "actions", "rewards", "terminations", "truncations")


def make_episodes(
    num_episodes: int,
    obs_dim: int,
    act_dim: int,
    *,
    seed: int,
    lengths: Sequence[int] | None = None,
    terminate_last: bool | None | Sequence[bool | None] = True,
) -> list[dict[str, np.ndarray]]:
    """Minari-style episodes: observations (T+1, obs_dim) float64 as gymnasium v5 gives them,
    actions (T, act_dim) float32 in [-1, 1], rewards (T,) float64, terminations and
    truncations (T,) bool.

    `terminate_last` says how each episode ends (one value for all, or one per episode):
    True a termination, False a truncation, None neither. Lengths default to 5..14 steps.
    """
    rng = np.random.default_rng(seed)
    if lengths is None:
        lengths = rng.integers(5, 15, size=num_episodes).tolist()
    if len(lengths) != num_episodes:
        raise ValueError(f"lengths has {len(lengths)} entries for {num_episodes} episodes")
    endings = (
        [terminate_last] * num_episodes
        if terminate_last is None or isinstance(terminate_last, bool)
        else list(terminate_last)
    )
    episodes = []
    for steps, ending in zip(lengths, endings, strict=True):
        terminations = np.zeros(steps, dtype=bool)
        truncations = np.zeros(steps, dtype=bool)
        if steps and ending is not None:
            (terminations if ending else truncations)[-1] = True
        episodes.append(
            {
                "observations": rng.normal(size=(steps + 1, obs_dim)),
                "actions": rng.uniform(-1.0, 1.0, size=(steps, act_dim)).astype(np.float32),
                "rewards": rng.normal(1.0, 0.5, size=steps),
                "terminations": terminations,
                "truncations": truncations,
            }
        )
    return episodes


def make_minari_dataset(
    dataset_id: str,
    episodes: list[dict[str, np.ndarray]],
    *,
    env_id: str | None = "Hopper-v5",
    ref_min_score: float | None = None,
    ref_max_score: float | None = None,
    extra_metadata: dict[str, Any] | None = None,
) -> Path:
    """Write `episodes` as a local Minari dataset and return its folder.

    Spaces come from the episodes' dims, so no environment is built; `env_id` is stored as the
    dataset's env spec (the registered spec when gymnasium knows the id), and the reference
    scores and `extra_metadata` (e.g. {"hipode": {...}}) as Minari metadata fields.
    """
    obs_dim = episodes[0]["observations"].shape[1]
    act_dim = episodes[0]["actions"].shape[1]
    buffers = [
        EpisodeBuffer(**{name: episode[name] for name in EPISODE_FIELDS}) for episode in episodes
    ]
    with warnings.catch_warnings():
        # Minari warns about every optional metadata field left empty
        warnings.simplefilter("ignore")
        dataset = minari.create_dataset_from_buffers(
            dataset_id,
            buffers,
            observation_space=gym.spaces.Box(-np.inf, np.inf, (obs_dim,), np.float64),
            action_space=gym.spaces.Box(-1.0, 1.0, (act_dim,), np.float32),
        )
    metadata: dict[str, Any] = dict(extra_metadata or {})
    if env_id is not None:
        metadata["env_spec"] = _env_spec_json(env_id)
    if ref_min_score is not None:
        metadata["ref_min_score"] = ref_min_score
    if ref_max_score is not None:
        metadata["ref_max_score"] = ref_max_score
    if metadata:
        dataset.storage.update_metadata(metadata)
    return Path(dataset.storage.data_path).parent


def _env_spec_json(env_id: str) -> str:
    """The registered spec as Minari stores it; a bare spec for ids gymnasium cannot serialize."""
    try:
        return gym.spec(env_id).to_json()
    except (gym.error.Error, ValueError):
        return EnvSpec(id=env_id).to_json()


def make_d4rl_file(
    path: str | Path,
    *,
    n: int,
    obs_dim: int,
    act_dim: int,
    seed: int,
    with_timeouts: bool = True,
    with_next_observations: bool = True,
    episode_length: int = 10,
    terminal_rows: Sequence[int] = (),
    attrs: dict[str, Any] | None = None,
    **overrides: np.ndarray | None,
) -> dict[str, np.ndarray]:
    """Write a D4RL-format file of `n` rows and return the true six fields (timeouts and
    next_observations included even when they are left out of the file).

    Episodes run `episode_length` steps and end with a timeout, except that a row listed in
    `terminal_rows` ends its episode with a terminal (the next episode starts after it).
    Within an episode next_observations[i] == observations[i+1]; a new episode starts from a
    fresh state. `overrides` replace a field as written (None leaves it out), for malformed files.
    """
    rng = np.random.default_rng(seed)
    terminal_set = set(terminal_rows)
    observations = np.empty((n, obs_dim), dtype=np.float32)
    next_observations = np.empty((n, obs_dim), dtype=np.float32)
    terminals = np.zeros(n, dtype=bool)
    timeouts = np.zeros(n, dtype=bool)
    state = rng.normal(size=obs_dim).astype(np.float32)
    step = 0
    for row in range(n):
        observations[row] = state
        next_observations[row] = state + rng.normal(scale=0.1, size=obs_dim).astype(np.float32)
        step += 1
        if row in terminal_set:
            terminals[row] = True
        elif step == episode_length:
            timeouts[row] = True
        if terminals[row] or timeouts[row]:
            state, step = rng.normal(size=obs_dim).astype(np.float32), 0
        else:
            state = next_observations[row]
    truth = {
        "observations": observations,
        "actions": rng.uniform(-1.0, 1.0, size=(n, act_dim)).astype(np.float32),
        "rewards": rng.normal(1.0, 0.5, size=n).astype(np.float32),
        "next_observations": next_observations,
        "terminals": terminals,
        "timeouts": timeouts,
    }
    written = dict(truth)
    if not with_timeouts:
        del written["timeouts"]
    if not with_next_observations:
        del written["next_observations"]
    for name, value in overrides.items():
        if value is None:
            written.pop(name, None)
        else:
            written[name] = value
    with h5py.File(path, "w") as f:
        for name, array in written.items():
            f.create_dataset(name, data=array)
        f.attrs.update(attrs or {})
    return truth
