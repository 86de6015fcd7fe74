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


def fast_bf16(device: torch.device) -> bool:
    """Whether bfloat16 matmuls run natively here (CUDA with bf16, CPUs with AVX512-BF16/AMX);
    elsewhere torch emulates them, far slower than fp32."""
    if device.type == "cuda":
        # bf16 tensor cores from compute capability 8 (Ampere); older GPUs emulate it
        return torch.cuda.get_device_capability(device)[0] >= 8
    check = getattr(torch.cpu, "_is_avx512_bf16_supported", None)
    return bool(check and check())
