"""Training precision chosen for the machine: bf16 autocast only where the hardware runs it.

On a CPU with native bf16 (AVX-512 BF16 or AMX) autocast makes the point encoder ~1.7x faster;
on an AVX2-only CPU oneDNN emulates bf16 and the same step is ~5x *slower* than fp32, so
``precision="auto"`` turns bf16 on only where it is native.
"""

from __future__ import annotations

import warnings

import torch

from torchrl_dalir.config import check_choice

PRECISIONS = ("auto", "bf16", "fp32")


def native_bf16(device: str | torch.device) -> bool:
    """Whether ``device`` runs bf16 matrix products natively (not emulated)."""
    device = torch.device(device)
    if device.type == "cuda":
        return torch.cuda.is_bf16_supported(including_emulation=False)
    if device.type == "cpu":  # AVX-512 without its BF16 extension (Skylake, Cascade Lake) emulates too
        return bool(torch.cpu._is_avx512_bf16_supported() or torch.cpu._is_amx_tile_supported())
    return False


def autocast_dtype(precision: str, device: str | torch.device) -> torch.dtype | None:
    """The autocast dtype for a ``precision`` setting (``auto``, ``bf16`` or ``fp32``) on
    ``device``; ``None`` means fp32. Forcing ``bf16`` where it is emulated warns."""
    check_choice("precision", precision, PRECISIONS)
    if precision == "fp32":
        return None
    native = native_bf16(device)
    if precision == "bf16" and not native:
        warnings.warn(
            f"precision=bf16 on {device} without native bf16 (CPU capability "
            f"{torch.backends.cpu.get_cpu_capability()}): training can be many times slower than "
            "fp32; precision=auto chooses for the machine",
            stacklevel=2,
        )
    return torch.bfloat16 if precision == "bf16" or native else None
