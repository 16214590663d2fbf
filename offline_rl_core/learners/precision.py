"""Float precision for training: fp32 by default, bf16 hidden-layer matmuls where the
CPU has native bf16.

bf16 matmuls pay off only with native support (AMX tiles, or AVX512-BF16); without
it oneDNN emulates them and they are slower than fp32. We detect, never assume.
Master weights, optimiser state and the thin input and output layers stay fp32
either way (see ``offline_rl_core.mlp_kernels``).
"""

from __future__ import annotations

from functools import lru_cache

import torch


@lru_cache(maxsize=1)
def cpu_bf16_flags() -> frozenset[str]:
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("flags"):
                    flags = set(line.split(":", 1)[1].split())
                    return frozenset(flags & {"amx_bf16", "amx_tile", "avx512_bf16"})
    except OSError:
        pass
    return frozenset()


def native_bf16() -> bool:
    return bool(cpu_bf16_flags() & {"amx_bf16", "avx512_bf16"})


def compute_dtype(deterministic: bool) -> torch.dtype:
    """The CPU hidden layer's matmul dtype: bf16 when allowed (not deterministic) and the
    CPU has it natively. (A GPU runs fp32 whatever this says, see ``networks``: at
    256x256 its step is bound by kernel launches, so bf16 would buy nothing there.)"""
    return torch.bfloat16 if not deterministic and native_bf16() else torch.float32
