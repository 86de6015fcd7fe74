"""Source ⊕ synthetic as a Minari dataset that `minari.load_dataset(ID)` loads.

Minari holds episodes, and an episode's next state is the following observation. The source
keeps its episodes (cut only where a row's next state is not the next row's state, which
Minari cannot hold); each synthetic transition becomes a one-step episode [s, s'] ending in
its own termination, or a truncation when it is not terminal, so no row is lost or invented.
Every episode carries the per-step info `is_synthetic`, and the dataset's metadata says which
episode ids are synthetic and where they came from.

The synthetic episodes are written straight into Minari's HDF5 layout (one group per episode,
as Minari's own writer makes them) because Minari's writer is slow and large for one-step
episodes; bench/minari_export.py compares the two.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from hipode_pipeline import console
from hipode_pipeline.data.minari_source import DATA_FILE, is_dataset_id
from hipode_pipeline.data.minari_write import dataset_dir, write_minari_dataset
from hipode_pipeline.data.transitions import Transitions
from hipode_pipeline.errors import DataFormatError, OverwriteError
from hipode_pipeline.merge import MergedData

SYNTHETIC_INFO = "is_synthetic"
METADATA_KEY = "hipode"  # Minari metadata entry: counts, the synthetic ids and provenance
PROGRESS_CHUNK = 4096


def source_episode_ends(real: Transitions) -> np.ndarray:
    """Last row of each episode: a termination, a truncation, a row whose next state is not
    the next row's state (a break Minari's layout cannot hold), and the final row."""
    breaks = np.zeros(len(real), bool)
    breaks[:-1] = np.any(real.next_observations[:-1] != real.observations[1:], axis=1)
    breaks[-1] = True
    return np.flatnonzero(real.terminals | real.timeouts | breaks)


def source_episodes(real: Transitions) -> list[dict[str, np.ndarray]]:
    """The source's episodes in Minari's form (T + 1 observations); one without an end of its
    own (a chain break or the file's last row) is marked truncated, its last state not terminal."""
    ends = source_episode_ends(real)
    starts = np.concatenate([[0], ends[:-1] + 1])
    episodes = []
    for start, end in zip(starts, ends + 1, strict=True):
        truncations = real.timeouts[start:end].copy()
        truncations[-1] |= not real.terminals[end - 1]
        episodes.append(
            {
                "observations": np.concatenate(
                    [real.observations[start:end], real.next_observations[end - 1 : end]]
                ),
                "actions": real.actions[start:end],
                "rewards": real.rewards[start:end],
                "terminations": real.terminals[start:end],
                "truncations": truncations,
                "infos": {SYNTHETIC_INFO: np.zeros(end - start + 1, bool)},
            }
        )
    return episodes


def one_step_episode(synthetic: Transitions, row: int) -> dict[str, np.ndarray]:
    """Synthetic row `row` as a Minari episode: [s, s'], cut (truncated) unless terminal."""
    terminal = synthetic.terminals[row : row + 1]
    return {
        "observations": np.stack([synthetic.observations[row], synthetic.next_observations[row]]),
        "actions": synthetic.actions[row : row + 1],
        "rewards": synthetic.rewards[row : row + 1],
        "terminations": terminal,
        "truncations": ~terminal,
        "infos": {SYNTHETIC_INFO: np.ones(2, bool)},
    }


def append_one_step_episodes(
    data_file: Path, synthetic: Transitions, first_id: int, *, show_progress: bool = True
) -> None:
    """Append each synthetic transition to Minari's episode file as its own episode."""
    with (
        h5py.File(data_file, "a", track_order=True) as f,
        console.progress(disable=not show_progress) as prog,
    ):
        bar = prog.add_task("minari episodes", total=len(synthetic), rate="", info="")
        started = time.perf_counter()
        # one HDF5 group per row is Minari's layout; the loop is over file objects
        for row in range(len(synthetic)):
            group = f.create_group(f"episode_{first_id + row}")
            group.attrs["id"] = first_id + row
            group.attrs["total_steps"] = 1
            episode = one_step_episode(synthetic, row)
            infos = group.create_group("infos")
            for name, values in episode.pop("infos").items():
                infos.create_dataset(name, data=values)
            for name, values in episode.items():
                group.create_dataset(name, data=values)
            if (row + 1) % PROGRESS_CHUNK == 0 or row + 1 == len(synthetic):
                elapsed = time.perf_counter() - started
                rate = console.rate_text(row + 1, elapsed, "rows")
                prog.update(bar, completed=row + 1, rate=rate)


def check_dataset_id(dataset_id: str, root: Path, force: bool) -> Path:
    """A Minari id (namespace/env/name-vN) that is free under `root`, unless `force`."""
    from minari.dataset.minari_dataset import parse_dataset_id

    try:
        valid = is_dataset_id(dataset_id) and parse_dataset_id(dataset_id)[2] is not None
    except (ValueError, TypeError):  # Minari's parser fails with either on a malformed id
        valid = False
    if not valid:
        raise DataFormatError(
            "--minari",
            "dataset id",
            "a Minari id with a version, e.g. hipode/hopper/medium-replay-hipode-v0",
            repr(dataset_id),
        )
    final = dataset_dir(root, dataset_id)
    if final.exists() and not force:
        raise OverwriteError(
            f"{final}: dataset '{dataset_id}' already exists; pass --force to replace it"
        )
    return final


def write_merged_minari(
    merged: MergedData,
    dataset_id: str,
    root: Path,
    *,
    force: bool = False,
    show_progress: bool = True,
) -> dict[str, Any]:
    """Write `merged` as Minari dataset `dataset_id` under `root` (staged, then moved in)."""
    started = time.perf_counter()
    real, synthetic = merged.real, merged.synthetic
    episodes = source_episodes(real)
    n_syn = 0 if synthetic is None else len(synthetic)
    ref_min, ref_max = merged.ref_scores()
    manifest = merged.artifact_manifest or {}
    record = {
        "source_episodes": len(episodes),
        "source_transitions": len(real),
        "synthetic_transitions": n_syn,
        "first_synthetic_episode": len(episodes),
        "synthetic_rule": "episodes with id >= first_synthetic_episode are one-step synthetic "
        f"transitions; every step's info '{SYNTHETIC_INFO}' says the same",
        "source": merged.source,
        "artifact_path": None if merged.artifact_path is None else merged.artifact_path.name,
        "artifact_checksum": manifest.get("checksum"),
        "artifact_manifest": manifest,
    }

    def add_synthetic(dataset: Any) -> None:
        if synthetic is None:
            return
        storage = dataset.storage
        append_one_step_episodes(
            storage.data_path / DATA_FILE, synthetic, len(episodes), show_progress=show_progress
        )
        storage.update_metadata(
            {
                "total_steps": len(real) + n_syn,
                "total_episodes": len(episodes) + n_syn,
                "dataset_size": storage.get_size(),
            }
        )

    path = write_minari_dataset(
        dataset_id,
        episodes,
        env_id=merged.env_id,
        root=root,
        staging=root / ".staging" / dataset_id.replace("/", "+"),
        ref_min_score=ref_min,
        ref_max_score=ref_max,
        algorithm_name="HIPODE",
        description=f"{merged.source['id']} with {n_syn} HIPODE synthetic transitions",
        extra_metadata={METADATA_KEY: record},
        force=force,
        finish=add_synthetic,
    )
    return {
        "dataset_id": dataset_id,
        "path": str(path),
        "env_id": merged.env_id,
        "source_episodes": len(episodes),
        "real": len(real),
        "synthetic": n_syn,
        "episodes": len(episodes) + n_syn,
        "artifact_checksum": manifest.get("checksum"),
        "seconds": round(time.perf_counter() - started, 2),
    }
