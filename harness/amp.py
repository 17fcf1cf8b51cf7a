"""Mixed precision in training (``Schedule.amp``, ``train --amp bf16``): a step's forward pass and loss run under
CPU autocast to bfloat16, where the CPU computes bfloat16 natively.

Autocast runs the dense convolutions, linear layers and matmuls in bfloat16; the models keep in float32 the heads'
outputs (losses, box decoding, the ranking of proposals), the coordinates that a matmul computes and the sparse
convolutions, whose small per-offset GEMMs gain nothing from bfloat16 (``models.base.no_autocast``,
``models.sparse.gather_gemm``). The master weights, AdamW's state, the checkpoint, the validation and the ONNX
export stay float32: only the training step changes, not what is trained into or read out of the weights.

The gate: bfloat16 is native on CPUs with AVX512-BF16 or AMX-BF16 (Intel Cooper Lake, Sapphire Rapids and later;
AMD Zen 4 and later have AVX512-BF16). Elsewhere oneDNN emulates it and a step is slower than in float32, so the
lever is refused there (``check_amp``) rather than quietly slowing a training down.
"""
from __future__ import annotations

import contextlib

import torch

AMP_DTYPES = {"bf16": torch.bfloat16}  # Schedule.amp -> autocast dtype
NATIVE_BF16_FLAGS = ("avx512_bf16", "amx_bf16")  # CPU flags (/proc/cpuinfo, torch.cpu.get_capabilities) of native bf16


def native_bf16() -> bool:
    """True when this CPU has one of ``NATIVE_BF16_FLAGS``."""
    caps = torch.cpu.get_capabilities()
    return any(caps.get(flag) for flag in NATIVE_BF16_FLAGS)


def check_amp(amp: str, device: str = "cpu") -> None:
    """Nothing when a training with ``Schedule.amp`` = ``amp`` can run here; else a ValueError that says why."""
    if not amp:
        return
    if amp not in AMP_DTYPES:
        raise ValueError(f"--amp {amp}: expected one of {', '.join(AMP_DTYPES)} (or none: float32)")
    if device != "cpu":
        raise ValueError(f"--amp {amp} is CPU autocast; got --device {device}")
    if not native_bf16():
        cpu = torch.cpu.get_capabilities().get("cpu_name") or "this CPU"
        raise ValueError(f"--amp {amp}: {cpu} has no native bfloat16 arithmetic (neither of the CPU flags "
                         f"{' / '.join(NATIVE_BF16_FLAGS)}), so bfloat16 would be emulated and slower than float32; "
                         "train without --amp")


def autocast(amp: str):
    """The context of a training step's forward pass and loss: CPU autocast to ``amp``'s dtype, nothing for ""."""
    return torch.autocast("cpu", dtype=AMP_DTYPES[amp]) if amp else contextlib.nullcontext()
