"""Z-scoring of states: every generator works in these units, the artifact stores raw values."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import TypeVar

import numpy as np
import torch

from hipode_pipeline.errors import DataFormatError
from hipode_pipeline.files import write_json_atomic

ArrayLike = TypeVar("ArrayLike", np.ndarray, torch.Tensor)


@dataclass(frozen=True, eq=False)
class StateNormalizer:
    """Per-dimension mean and std of the source's states (std already includes eps)."""

    mean: np.ndarray  # (ds,) float32
    std: np.ndarray  # (ds,) float32, strictly positive

    @classmethod
    def fit(cls, states: np.ndarray, eps: float = 1e-3) -> StateNormalizer:
        """Mean and std over rows; eps keeps constant dimensions finite."""
        states = np.asarray(states, dtype=np.float64)
        return cls(
            mean=states.mean(axis=0).astype(np.float32),
            std=(states.std(axis=0) + eps).astype(np.float32),
        )

    def normalize(self, x: ArrayLike) -> ArrayLike:
        mean, std = self._as(x)
        return (x - mean) / std

    def denormalize(self, x: ArrayLike) -> ArrayLike:
        mean, std = self._as(x)
        return x * std + mean

    def _as(self, x):
        if isinstance(x, torch.Tensor):
            return (
                torch.as_tensor(self.mean, dtype=x.dtype, device=x.device),
                torch.as_tensor(self.std, dtype=x.dtype, device=x.device),
            )
        dtype = x.dtype if np.issubdtype(np.asarray(x).dtype, np.floating) else np.float32
        return self.mean.astype(dtype), self.std.astype(dtype)

    def to_dict(self) -> dict[str, list[float]]:
        return {"mean": self.mean.tolist(), "std": self.std.tolist()}

    @classmethod
    def from_dict(cls, data: dict, origin: str | Path = "<dict>") -> StateNormalizer:
        for key in ("mean", "std"):
            if key not in data:
                raise DataFormatError(origin, key, "a list of floats", "nothing (missing)")
        mean = np.asarray(data["mean"], dtype=np.float32)
        std = np.asarray(data["std"], dtype=np.float32)
        if mean.ndim != 1 or mean.shape != std.shape:
            raise DataFormatError(
                origin, "std", f"a list of {mean.shape} floats like 'mean'", std.shape
            )
        if not (np.all(np.isfinite(mean)) and np.all(std > 0)):
            raise DataFormatError(origin, "std", "finite mean and positive std", std.tolist())
        return cls(mean=mean, std=std)

    def save(self, path: Path) -> None:
        """Write as JSON atomically."""
        write_json_atomic(path, self.to_dict())

    @classmethod
    def load(cls, path: Path) -> StateNormalizer:
        path = Path(path)
        try:
            data = json.loads(path.read_text())
        except json.JSONDecodeError as error:
            raise DataFormatError(path, "(file)", "valid JSON", str(error)) from None
        return cls.from_dict(data, origin=path)
