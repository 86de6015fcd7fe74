"""Which torch device the models train and sample on."""

from __future__ import annotations

import torch

from hipode_pipeline.errors import DeviceUnavailableError


def select_device(preferred: str | None = None) -> torch.device:
    """CUDA when present, else CPU; `preferred` ("cpu", "cuda", "cuda:1") overrides the choice."""
    if preferred is None or preferred == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        device = torch.device(preferred)
    except RuntimeError:
        raise DeviceUnavailableError(
            f"device '{preferred}': expected 'auto', 'cpu' or 'cuda[:index]'"
        ) from None
    if device.type == "cuda":
        if not torch.cuda.is_available():
            raise DeviceUnavailableError(f"device '{preferred}': expected a CUDA GPU, found none")
        if device.index is not None and device.index >= torch.cuda.device_count():
            raise DeviceUnavailableError(
                f"device '{preferred}': expected an index below {torch.cuda.device_count()}"
            )
    elif device.type != "cpu":
        raise DeviceUnavailableError(
            f"device '{preferred}': expected 'auto', 'cpu' or 'cuda[:index]'"
        )
    return device
