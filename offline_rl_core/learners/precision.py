"""Float precision for training: fp32 by default, bf16 autocast where the CPU has it.

bf16 matmuls pay off only with native support (AMX tiles, or AVX512-BF16); without
it oneDNN emulates them and they are slower than fp32. We detect, never assume.
Master weights and the optimiser stay fp32 either way.
"""

from __future__ import annotations

import contextlib
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


def autocast_context(deterministic: bool):
    """bf16 autocast when allowed (not deterministic) and native; else a no-op.

    The weight-cast cache is off: the loop runs every optimiser step inside one context,
    and autocast's cache would keep serving the first bf16 copy of each weight after the
    optimiser has updated its fp32 master in place (training then stalls). Re-casting
    costs nothing measurable at these sizes.
    """
    if deterministic or not native_bf16():
        return contextlib.nullcontext()
    return torch.autocast("cpu", dtype=torch.bfloat16, cache_enabled=False)
