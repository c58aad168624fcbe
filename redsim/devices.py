"""Where and in what precision redsim computes: the dtype names every option takes, and the device check."""

from __future__ import annotations

from typing import Any

import torch

DTYPES = {"float32": torch.float32, "float64": torch.float64}
"""The dtypes an env, a fit or a benchmark runs in, by the name its option takes."""


def check_dtype(dtype: Any, what: str = "dtype") -> torch.dtype:
    """``dtype`` if it is one of :data:`DTYPES` (torch.float32 or torch.float64), or a ValueError naming ``what``."""
    if dtype not in DTYPES.values():
        raise ValueError(f"{what} must be torch.float32 or torch.float64, got {dtype}")
    return dtype


def check_device(device: Any) -> str:
    """``device`` as the string torch takes, or a ValueError where redsim cannot run on it.

    redsim runs on ``"cpu"`` and ``"cuda[:N]"``: a CUDA device needs a CUDA build of torch and a GPU of that
    index (``torch.cuda.device_count()``).
    """
    try:
        parsed = torch.device(device)
    except (RuntimeError, TypeError):
        raise ValueError(f"device must be 'cpu' or 'cuda[:N]', got {device!r}") from None
    if parsed.type not in ("cpu", "cuda"):
        raise ValueError(f"device must be 'cpu' or 'cuda[:N]', got {device!r}")
    if parsed.type == "cuda":
        if not torch.cuda.is_available():
            raise ValueError(
                f"device {device!r} is not available: torch.cuda.is_available() is False (a CPU build or no GPU)"
            )
        if parsed.index is not None and parsed.index >= torch.cuda.device_count():
            raise ValueError(f"device {device!r} is not available: torch sees {torch.cuda.device_count()} GPU(s)")
    return str(parsed)
