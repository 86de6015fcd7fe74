"""The one in-memory form of a dataset: flat float32 transition arrays plus where they came from."""

from __future__ import annotations

import hashlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from hipode_pipeline.errors import DataFormatError

FIELDS = ("observations", "actions", "rewards", "next_observations", "terminals", "timeouts")


@dataclass(frozen=True, eq=False)
class Transitions:
    """N transitions (s, a, r, s', terminal, timeout) as flat arrays.

    terminal means the MDP ended (no bootstrapping); timeout means the episode was cut by a
    time limit (bootstrap). They are never merged.
    """

    observations: np.ndarray  # (N, obs_dim) float32
    actions: np.ndarray  # (N, act_dim) float32
    rewards: np.ndarray  # (N,) float32
    next_observations: np.ndarray  # (N, obs_dim) float32
    terminals: np.ndarray  # (N,) bool
    timeouts: np.ndarray  # (N,) bool

    def __len__(self) -> int:
        return int(self.rewards.shape[0])

    @property
    def obs_dim(self) -> int:
        return int(self.observations.shape[1])

    @property
    def act_dim(self) -> int:
        return int(self.actions.shape[1])

    def arrays(self) -> dict[str, np.ndarray]:
        return {name: getattr(self, name) for name in FIELDS}

    def sha256(self) -> str:
        """Content hash over every field's name, dtype, shape and bytes (identifies a source)."""
        digest = hashlib.sha256()
        for name, array in self.arrays().items():
            digest.update(f"{name}:{array.dtype.str}:{array.shape}".encode())
            digest.update(np.ascontiguousarray(array).data)
        return digest.hexdigest()

    def episode_ends(self) -> np.ndarray:
        """Indices of transitions that end an episode (terminal or timeout)."""
        return np.flatnonzero(self.terminals | self.timeouts)

    def episode_returns(self) -> np.ndarray:
        """Sum of rewards per episode, in order (float64); a trailing unfinished one counts."""
        ends = self.terminals | self.timeouts
        episode = np.concatenate(([0], np.cumsum(ends)[:-1]))
        return np.bincount(episode, weights=self.rewards.astype(np.float64))

    @classmethod
    def concatenate(cls, parts: list[Transitions]) -> Transitions:
        return cls(**{name: np.concatenate([getattr(p, name) for p in parts]) for name in FIELDS})


@dataclass(frozen=True)
class SourceInfo:
    """Where a Transitions object came from; recorded in every artifact built from it."""

    id: str  # Minari id or file path
    env_id: str | None  # gymnasium id, e.g. Hopper-v5
    ref_min_score: float | None  # D4RL random return
    ref_max_score: float | None  # D4RL expert return
    sha256: str  # Transitions.sha256()
    n: int  # number of transitions
    format: str  # "minari" | "d4rl-hdf5"
    metadata: dict[str, Any] = field(default_factory=dict)  # recipe, seeds, policy returns, ...

    def to_dict(self) -> dict[str, Any]:
        return {
            "id": self.id,
            "env_id": self.env_id,
            "ref_min_score": self.ref_min_score,
            "ref_max_score": self.ref_max_score,
            "sha256": self.sha256,
            "n": self.n,
            "format": self.format,
            "metadata": self.metadata,
        }


def validate_transitions(arrays: dict[str, np.ndarray], origin: str | Path) -> Transitions:
    """Check shapes, dtypes and finiteness of raw arrays and return float32/bool Transitions.

    Every violation raises DataFormatError naming `origin`, the field and what was expected.
    """
    for name in FIELDS:
        if name not in arrays:
            raise DataFormatError(origin, name, "a dataset field", "nothing (missing)")
    obs = arrays["observations"]
    if obs.ndim != 2 or obs.shape[0] == 0 or obs.shape[1] == 0:
        raise DataFormatError(
            origin, "observations", "a non-empty 2-D array (N, obs_dim)", obs.shape
        )
    n, obs_dim = obs.shape
    act = arrays["actions"]
    if act.ndim != 2 or act.shape[1] == 0:
        raise DataFormatError(origin, "actions", f"a 2-D array ({n}, act_dim)", act.shape)
    expected_shapes = {
        "actions": (n, act.shape[1]),
        "rewards": (n,),
        "next_observations": (n, obs_dim),
        "terminals": (n,),
        "timeouts": (n,),
    }
    for name, shape in expected_shapes.items():
        found = arrays[name].shape
        # (N, 1) rewards and flags are common in older files: accept and flatten
        if name in ("rewards", "terminals", "timeouts") and found == (n, 1):
            continue
        if found != shape:
            raise DataFormatError(origin, name, f"shape {shape}", found)
    converted = {}
    for name in FIELDS:
        array = np.asarray(arrays[name])
        if array.ndim == 2 and name in ("rewards", "terminals", "timeouts"):
            array = array[:, 0]
        if name in ("terminals", "timeouts"):
            if not (array.dtype == np.bool_ or np.issubdtype(array.dtype, np.number)):
                raise DataFormatError(origin, name, "a boolean or 0/1 array", array.dtype)
            if array.dtype != np.bool_ and not np.isin(array, (0, 1)).all():
                raise DataFormatError(
                    origin, name, "only 0/1 values", np.unique(array)[:5].tolist()
                )
            converted[name] = array.astype(np.bool_)
            continue
        if not np.issubdtype(array.dtype, np.number) or np.issubdtype(
            array.dtype, np.complexfloating
        ):
            raise DataFormatError(origin, name, "a real-valued numeric array", array.dtype)
        with np.errstate(over="ignore"):  # an out-of-range float64 becomes inf, reported just below
            array = array.astype(np.float32, copy=False)
        bad = ~np.isfinite(array)
        if bad.any():
            first = int(np.argwhere(bad)[0][0])
            raise DataFormatError(
                origin, name, "finite values", f"{int(bad.sum())} NaN/inf (first at row {first})"
            )
        converted[name] = np.ascontiguousarray(array)
    both = converted["terminals"] & converted["timeouts"]
    if both.any():
        # a step can be both in gymnasium; the terminal wins since nothing follows it
        converted["timeouts"] = converted["timeouts"] & ~converted["terminals"]
    return Transitions(**converted)
