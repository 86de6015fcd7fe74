"""Minari datasets from the local store, read straight from Minari's HDF5 storage.

Layout: `<root>/<dataset id>/data/metadata.json` beside `main_data.hdf5`, which holds one group
`episode_<i>` per episode with observations (T+1, ds), actions (T, da), rewards, terminations
and truncations (T,). We read those arrays with h5py rather than through `minari.load_dataset`,
which may build the environment to recover spaces and decodes every episode's infos.
Nothing named in the metadata (env entry point, spaces) is instantiated or imported.
"""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from hipode_pipeline.data.d4rl_source import (
    check_field_header,
    check_memory,
    float_or_none,
    open_hdf5,
)
from hipode_pipeline.data.transitions import SourceInfo, Transitions, validate_transitions
from hipode_pipeline.errors import DataFormatError, DatasetNotFoundError
from hipode_pipeline.paths import datasets_root

FORMAT = "minari"
METADATA_FILE = "metadata.json"
DATA_FILE = "main_data.hdf5"
EPISODE_FIELDS = ("observations", "actions", "rewards", "terminations", "truncations")
# Minari ids: (namespace/)(env/)name(-vN); each part a plain name, so an id never leaves the root
DATASET_ID_PATTERN = re.compile(r"^[A-Za-z0-9_.-]+(/[A-Za-z0-9_.-]+){0,2}$")


def dataset_dir(dataset_id: str, root: Path | None = None) -> Path:
    """The folder a Minari id occupies under the dataset root."""
    return (root or datasets_root()) / dataset_id


def is_dataset_id(text: str) -> bool:
    """Whether `text` has the shape of a Minari id (and no path tricks such as '..')."""
    return bool(DATASET_ID_PATTERN.match(text)) and ".." not in text.split("/")


def has_local_dataset(dataset_id: str, root: Path | None = None) -> bool:
    return (
        is_dataset_id(dataset_id)
        and (dataset_dir(dataset_id, root) / "data" / METADATA_FILE).is_file()
    )


def read_metadata(data_dir: Path) -> dict[str, Any]:
    """A dataset's metadata.json as a dict, with a clear error when it is not JSON."""
    path = data_dir / METADATA_FILE
    try:
        metadata = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as error:
        raise DataFormatError(
            path, "metadata", "a JSON object (Minari's metadata)", f"unreadable ({error})"
        ) from None
    if not isinstance(metadata, dict):
        raise DataFormatError(
            path, "metadata", "a JSON object (Minari's metadata)", type(metadata).__name__
        )
    return metadata


def env_id_of(metadata: dict[str, Any]) -> str | None:
    """The gymnasium id in `env_spec` (else `eval_env_spec`), read as a plain string."""
    entry = env_id_entry(metadata)
    return entry[1] if entry else None


def env_id_entry(metadata: dict[str, Any]) -> tuple[str, str] | None:
    """(field, env id): where `env_id_of` finds the id, e.g. ("env_spec.id", "Hopper-v5")."""
    for key in ("env_spec", "eval_env_spec"):
        spec = metadata.get(key)
        if isinstance(spec, str):
            try:
                spec = json.loads(spec)
            except json.JSONDecodeError:
                continue
        if isinstance(spec, dict) and isinstance(spec.get("id"), str):
            return f"{key}.id", spec["id"]
    return None


def ref_scores_of(metadata: dict[str, Any]) -> tuple[float | None, float | None]:
    """The dataset's own reference returns; (None, None) unless both are finite numbers."""
    low, high = (
        float_or_none(metadata.get("ref_min_score")),
        float_or_none(metadata.get("ref_max_score")),
    )
    return (low, high) if low is not None and high is not None else (None, None)


def load_minari(dataset_id: str, root: Path | None = None) -> tuple[Transitions, SourceInfo]:
    """Flatten a local Minari dataset: s = observations[:-1], s' = observations[1:] per episode,
    terminations -> terminals, truncations -> timeouts (never merged), cast to float32 once.

    SourceInfo.metadata is Minari's metadata plus `episodes`, `episodes_without_end` and `notes`;
    reference scores are the dataset's own (None when it has none: `load_source` completes them).
    """
    if not has_local_dataset(dataset_id, root):
        where = (
            dataset_dir(dataset_id, root) / "data" / METADATA_FILE
            if is_dataset_id(dataset_id)
            else root
        )
        raise DatasetNotFoundError(
            f"no Minari dataset '{dataset_id}' in the local store (looked for {where}); "
            "downloads are not available here: "
            f"copy the dataset folder into {root or datasets_root()}"
        )
    data_dir = dataset_dir(dataset_id, root) / "data"
    metadata = read_metadata(data_dir)
    metadata_path = data_dir / METADATA_FILE
    if metadata.get("data_format", "hdf5") != "hdf5":
        raise DataFormatError(
            metadata_path,
            "data_format",
            "'hdf5' (Minari's HDF5 storage)",
            repr(metadata.get("data_format")),
        )
    episodes = metadata.get("total_episodes")
    if not isinstance(episodes, int) or episodes < 1:
        raise DataFormatError(metadata_path, "total_episodes", "a positive integer", repr(episodes))
    steps = metadata.get("total_steps")
    if not isinstance(steps, int) or steps < 1:
        raise DataFormatError(metadata_path, "total_steps", "a positive integer", repr(steps))
    data_path = data_dir / DATA_FILE
    if not data_path.is_file():
        raise DataFormatError(
            data_path,
            "file",
            f"Minari's episode file {DATA_FILE} beside {METADATA_FILE}",
            "no such file",
        )
    with open_hdf5(data_path) as f:
        lengths, arrays = _read_episodes(f, data_path, episodes, steps)
    with np.errstate(over="ignore"):
        transitions = validate_transitions(arrays, data_path)
    ends = transitions.terminals | transitions.timeouts
    last_rows = np.cumsum(lengths)[lengths > 0] - 1
    without_end = int((~ends[last_rows]).sum())
    notes = []
    if without_end:
        notes.append(f"{without_end} episode(s) end with neither a termination nor a truncation")
    ref_min, ref_max = ref_scores_of(metadata)
    info = SourceInfo(
        id=dataset_id,
        env_id=env_id_of(metadata),
        ref_min_score=ref_min,
        ref_max_score=ref_max,
        sha256=transitions.sha256(),
        n=len(transitions),
        format=FORMAT,
        metadata={
            **metadata,
            "episodes": episodes,
            "episodes_without_end": without_end,
            "notes": notes,
        },
    )
    return transitions, info


class _FlatBuffers:
    """Preallocated float32 arrays every episode is read into, sized from Minari's metadata."""

    def __init__(self, data_path: Path, episodes: int, steps: int, obs_dim: int, act_dim: int):
        check_memory(data_path, "observations", steps, obs_dim, act_dim)
        # T+1 observation rows per episode
        self.observations = np.empty((steps + episodes, obs_dim), dtype=np.float32)
        self.actions = np.empty((steps, act_dim), dtype=np.float32)
        self.rewards = np.empty(steps, dtype=np.float32)
        # float, not bool, so a stray 2 or NaN survives to validation and is reported
        self.terminations = np.empty(steps, dtype=np.float64)
        self.truncations = np.empty(steps, dtype=np.float64)


def _read_episodes(
    f: h5py.File, data_path: Path, episodes: int, steps: int
) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """Check and read every episode in one pass, then flatten (s, s') with one gather.

    Each episode's shapes and dtypes are checked from its metadata before it is read; the
    buffers are sized from total_steps, which must equal the sum of the episode lengths.
    """
    lengths = np.empty(episodes, dtype=np.int64)
    buffers: _FlatBuffers | None = None
    obs_dim = act_dim = None
    o = s = 0
    with np.errstate(over="ignore", invalid="ignore"):
        for index in range(episodes):
            prefix = f"episode_{index}/"
            fields = _episode_fields(f, data_path, index)
            t = check_field_header(
                fields["rewards"], data_path, prefix + "rewards", rows=None, flag=True
            )[0]
            obs_dim = check_field_header(
                fields["observations"],
                data_path,
                prefix + "observations",
                rows=t + 1,
                feature_dim=obs_dim,
            )[1]
            act_dim = check_field_header(
                fields["actions"], data_path, prefix + "actions", rows=t, feature_dim=act_dim
            )[1]
            for name in ("terminations", "truncations"):
                check_field_header(fields[name], data_path, prefix + name, rows=t, flag=True)
            if s + t > steps:
                raise DataFormatError(
                    data_path.parent / METADATA_FILE,
                    "total_steps",
                    "the sum of the episode lengths",
                    f"{steps}, exceeded at episode {index}",
                )
            if buffers is None:
                buffers = _FlatBuffers(data_path, episodes, steps, obs_dim, act_dim)
            buffers.observations[o : o + t + 1] = _read(fields, "observations", data_path, prefix)
            buffers.actions[s : s + t] = _read(fields, "actions", data_path, prefix)
            buffers.rewards[s : s + t] = _read(fields, "rewards", data_path, prefix).reshape(t)
            buffers.terminations[s : s + t] = _read(
                fields, "terminations", data_path, prefix
            ).reshape(t)
            buffers.truncations[s : s + t] = _read(
                fields, "truncations", data_path, prefix
            ).reshape(t)
            # drop handles per episode: h5py closes thousands of open ones slowly at file close
            del fields
            lengths[index] = t
            o, s = o + t + 1, s + t
    if s != steps:
        raise DataFormatError(
            data_path.parent / METADATA_FILE,
            "total_steps",
            "the sum of the episode lengths",
            f"{steps} for {s} steps",
        )
    obs_starts = np.concatenate(([0], np.cumsum(lengths + 1)[:-1]))
    step_starts = np.concatenate(([0], np.cumsum(lengths)[:-1]))
    _check_finite(data_path, "observations", buffers.observations, obs_starts)
    _check_finite(data_path, "actions", buffers.actions, step_starts)
    _check_finite(data_path, "rewards", buffers.rewards, step_starts)
    # row of s for each transition: its episode's first observation row plus its step index
    state_rows = np.repeat(obs_starts, lengths) + (
        np.arange(steps) - np.repeat(step_starts, lengths)
    )
    return lengths, {
        "observations": buffers.observations[state_rows],
        "actions": buffers.actions,
        "rewards": buffers.rewards,
        "next_observations": buffers.observations[state_rows + 1],
        "terminals": buffers.terminations,
        "timeouts": buffers.truncations,
    }


def _episode_fields(f: h5py.File, data_path: Path, index: int) -> dict[str, Any]:
    """The five fields of one episode as low-level dataset handles.

    Measured here, h5py's high-level lookup and read cost ~250 us per field against ~60 us for
    the low-level calls: with thousands of episodes that is most of the load time.
    """
    group = f.get(f"episode_{index}")
    if not isinstance(group, h5py.Group):
        raise DataFormatError(
            data_path,
            f"episode_{index}",
            f"an episode group (total_episodes in {METADATA_FILE})",
            "missing",
        )
    fields = {}
    for name in EPISODE_FIELDS:
        try:
            fields[name] = h5py.h5d.open(group.id, name.encode())
        except KeyError:
            found = (
                "a group (dict-valued spaces are not supported)"
                if name in group
                else "nothing (missing)"
            )
            raise DataFormatError(
                data_path, f"episode_{index}/{name}", "an HDF5 dataset of numbers", found
            ) from None
    return fields


def _check_finite(
    data_path: Path, name: str, array: np.ndarray, episode_starts: np.ndarray
) -> None:
    """Name the episode and step of the first NaN/inf, which a flat row index would hide."""
    bad = ~np.isfinite(array)
    if bad.ndim == 2:
        bad = bad.any(axis=1)
    if bad.any():
        row = int(np.argmax(bad))
        episode = int(np.searchsorted(episode_starts, row, side="right") - 1)
        step = row - int(episode_starts[episode])
        raise DataFormatError(
            data_path,
            f"episode_{episode}/{name}",
            "finite values",
            f"{int(bad.sum())} row(s) with NaN/inf, first at step {step}",
        )


def _read(fields: dict[str, Any], name: str, data_path: Path, prefix: str) -> np.ndarray:
    dataset = fields[name]
    array = np.empty(dataset.shape, dtype=dataset.dtype)
    try:
        dataset.read(h5py.h5s.ALL, h5py.h5s.ALL, array)
        return array
    except (OSError, RuntimeError, ValueError) as error:
        raise DataFormatError(
            data_path, prefix + name, "readable data", f"a truncated or corrupt dataset ({error})"
        ) from None
