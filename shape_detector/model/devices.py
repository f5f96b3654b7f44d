"""Which device and arithmetic a forward runs on: CUDA or CPU, bfloat16 on CPUs with AMX; how
many CPU cores this process may use."""

from __future__ import annotations

import os
from typing import TYPE_CHECKING, Any

from .config import PRECISIONS

if TYPE_CHECKING:
    import torch

#: ``precision="auto"``: batches of at least this many frustums run in bfloat16 on CPUs with
#: AMX, smaller ones in fp32 (bf16 has a fixed cost that only larger batches earn back)
AUTO_BF16_MIN_BATCH = 4


def bf16_min_batch(precision: str, device: Any) -> int | None:
    """The batch size from which a forward runs in bfloat16 under ``precision``: None =
    never (``"fp32"``, or ``"auto"`` on a device without AMX), 0 = always (``"bf16"``),
    :data:`AUTO_BF16_MIN_BATCH` for ``"auto"`` on a CPU with AMX."""
    if precision not in PRECISIONS:
        raise ValueError(f"precision must be one of {PRECISIONS}, got {precision!r}")
    if precision == "bf16":
        return 0
    if precision == "auto" and getattr(device, "type", str(device)) == "cpu" and cpu_has_amx():
        return AUTO_BF16_MIN_BATCH
    return None


def cpu_has_amx() -> bool:
    """Whether this CPU has AMX tiles (bfloat16 matrix units); False when torch cannot tell."""
    try:
        import torch

        return bool(torch.cpu._is_amx_tile_supported())
    except Exception:  # noqa: BLE001 - a private torch helper: absent means unknown
        return False


def resolve_device(device: str | torch.device | None) -> torch.device:
    """``"auto"``/None -> cuda when available else cpu; otherwise ``torch.device(device)``."""
    import torch

    if device is None or str(device) == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(device)


def usable_cores() -> int:
    """CPU cores this process may run on (its affinity where the OS tells, else all)."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
