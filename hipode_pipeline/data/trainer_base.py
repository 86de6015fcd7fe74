"""What every behaviour-policy trainer of `hipode collect` shares: settings read from a recipe
section, the progress counters, and the checkpoint's identity check and progress fields."""

from __future__ import annotations

import json
from collections import deque
from dataclasses import asdict, fields
from typing import Any, ClassVar

import numpy as np

from hipode_pipeline.data.env_batch import rng_from_state
from hipode_pipeline.errors import DataFormatError


class TrainerConfig:
    """Mixin of the trainers' frozen config dataclasses: strict reading, plain writing."""

    # field -> its allowed values, checked on construction and, naming the file, on reading
    CHOICES: ClassVar[dict[str, Any]] = {}

    def __post_init__(self) -> None:
        for name, allowed in self.CHOICES.items():
            if getattr(self, name) not in allowed:
                raise ValueError(
                    f"{name}: expected one of {sorted(allowed)}, found {getattr(self, name)!r}"
                )

    @classmethod
    def from_dict(cls, values: dict[str, Any], origin: str = "trainer config"):
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(values) - known)
        if unknown:
            raise DataFormatError(origin, unknown[0], f"one of {sorted(known)}", "an unknown key")
        for name, allowed in cls.CHOICES.items():
            if name in values and values[name] not in allowed:
                raise DataFormatError(origin, name, f"one of {sorted(allowed)}", repr(values[name]))
        return cls(**values)

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


class BehaviourTrainer:
    """Progress of a trainer over its envs; subclasses add the learning and the rest of the
    checkpoint (`name` says which trainer a checkpoint error is about)."""

    name = "trainer"

    def __init__(self, env_id: str, config: TrainerConfig, seed: int, recent_episodes: int):
        self.env_id, self.config, self.seed = env_id, config, seed
        self.rng = np.random.default_rng(seed)
        self.recent_returns: deque[float] = deque(maxlen=recent_episodes)
        self.episodes_done = 0
        self.steps = 0
        self.iteration = 0

    def recent_return(self) -> float:
        """Mean raw return of the last completed training episodes (nan before the first)."""
        return float(np.mean(self.recent_returns)) if self.recent_returns else float("nan")

    def progress_state(self) -> dict[str, Any]:
        return {
            "env_id": self.env_id,
            "config": json.dumps(self.config.to_dict()),
            "seed": self.seed,
            "steps": self.steps,
            "iteration": self.iteration,
            "episodes_done": self.episodes_done,
            "recent_returns": list(self.recent_returns),
            "rng": json.dumps(self.rng.bit_generator.state),
        }

    def load_progress(self, state: dict[str, Any], origin: object) -> None:
        """Check the checkpoint is of this env and config, then restore the counters."""
        if state["env_id"] != self.env_id or json.loads(state["config"]) != self.config.to_dict():
            raise DataFormatError(
                origin,
                "config",
                f"a checkpoint of {self.env_id} with this {self.name} config "
                "(delete the collect work folder or use another seed)",
                state["env_id"],
            )
        self.steps, self.iteration = int(state["steps"]), int(state["iteration"])
        self.episodes_done = int(state["episodes_done"])
        self.recent_returns = deque(state["recent_returns"], maxlen=self.recent_returns.maxlen)
        self.rng = rng_from_state(json.loads(state["rng"]))
