"""The number format the core network runs in: bfloat16 autocast where the hardware has it.

Only the core network's matrix products run in bfloat16 (``torch.autocast``); features,
normalisers, graph geometry and time integration stay in float32/float64. ``precision`` is
``"auto"`` (bfloat16 on CUDA GPUs of compute capability 8 or more and on CPUs with bfloat16
matrix instructions, AMX-BF16 or AVX512-BF16, for networks at least :data:`CPU_BF16_MIN_LATENT`
wide; float32 elsewhere), ``"bf16"`` (always; CPUs
without those instructions emulate it, correctly but several times slower than float32) or
``"f32"``.
"""

from __future__ import annotations

import functools
from contextlib import AbstractContextManager
from pathlib import Path

import torch

__all__ = ["PRECISIONS", "CPU_BF16_MIN_LATENT", "cpu_has_bf16", "bf16_supported", "network_dtype", "network_autocast"]

PRECISIONS = ("auto", "bf16", "f32")
# On a CPU, narrow networks are faster in float32: their products are too small for bfloat16's
# speed to pay for the casts. Measured on the press graph (1,300 nodes, 6 levels, one thread of an
# AMX-BF16/AVX512-BF16 Xeon): latent 32 f32 29 ms / bf16 35 ms, 64: 38 / 50 ms, 96: 88 / 52 ms, 128: 103 / 65 ms.
CPU_BF16_MIN_LATENT = 96


@functools.cache
def cpu_has_bf16() -> bool:
    """Whether this CPU multiplies bfloat16 matrices in hardware (AMX-BF16 or AVX512-BF16)."""
    probes = [getattr(torch.cpu, name, None) for name in ("_is_amx_tile_supported", "_is_avx512_bf16_supported")]
    if all(callable(probe) for probe in probes):
        return any(probe() for probe in probes)
    cpuinfo = Path("/proc/cpuinfo")
    flags = cpuinfo.read_text().split() if cpuinfo.exists() else []
    return "amx_bf16" in flags or "avx512_bf16" in flags


def bf16_supported(device: torch.device | str) -> bool:
    """Whether ``device`` runs bfloat16 matrix products faster than float32 ones."""
    device = torch.device(device)
    if device.type == "cuda":
        return torch.cuda.get_device_capability(device)[0] >= 8
    return device.type == "cpu" and cpu_has_bf16()


def network_dtype(precision: str, device: torch.device | str, latent: int | None = None) -> torch.dtype:
    """The dtype of the core network's products for ``precision`` on ``device``; ``latent``: the
    network's width (``auto`` keeps float32 on a CPU below :data:`CPU_BF16_MIN_LATENT`)."""
    if precision not in PRECISIONS:
        raise ValueError(f"precision must be one of {', '.join(map(repr, PRECISIONS))}, got {precision!r}")
    if precision == "auto":
        narrow = torch.device(device).type == "cpu" and latent is not None and latent < CPU_BF16_MIN_LATENT
        return torch.bfloat16 if bf16_supported(device) and not narrow else torch.float32
    return torch.bfloat16 if precision == "bf16" else torch.float32


def network_autocast(dtype: torch.dtype, device: torch.device | str) -> AbstractContextManager:
    """bfloat16 autocast on ``device`` when ``dtype`` is bfloat16; a no-op for float32."""
    return torch.autocast(torch.device(device).type, dtype=torch.bfloat16, enabled=dtype == torch.bfloat16)
