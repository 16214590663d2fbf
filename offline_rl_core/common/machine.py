"""Facts about this machine, and a cache of what was measured on it.

What a CPU can run fast is not predictable from its flags alone, so a few things are
measured once per machine and kept in ``~/.cache/pusher-rl/`` (the hidden layer's kernels,
the learners' step rates, the chapter's loop time): ``machine_key`` names a measurement by
the CPU model, its flags, the torch build and what was measured, so a cache copied to
another machine is never read there, and every later run on this one makes the same choice.
"""

from __future__ import annotations

import functools
import hashlib
import json
import os
from pathlib import Path

from .atomic import write_text_atomic

ISA_FLAGS = ("avx2", "fma", "avx512f", "avx512_bf16", "amx_tile", "amx_bf16")
CACHE_VERSION = 1


@functools.lru_cache(maxsize=1)
def cpu_model_and_flags() -> tuple[str, frozenset[str]]:
    model, flags = "", frozenset()
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name") and not model:
                    model = line.split(":", 1)[1].strip()
                elif line.startswith("flags") and not flags:
                    flags = frozenset(line.split(":", 1)[1].split())
    except OSError:
        pass
    return model, flags


# Environment variables that cap the instruction set of torch's own kernels, oneDNN's and
# MKL's; ``offline-rl bench --isa avx2`` sets all three to run as an AVX2-only CPU would.
ISA_LIMIT_ENV = {"ATEN_CPU_CAPABILITY": "avx2", "ONEDNN_MAX_CPU_ISA": "AVX2", "MKL_ENABLE_INSTRUCTIONS": "AVX2"}


def isa_limits() -> dict[str, str]:
    """The instruction-set caps set in the environment (name -> value)."""
    return {k: os.environ[k] for k in ISA_LIMIT_ENV if os.environ.get(k, "").strip()}


def _limited_to_avx2() -> bool:
    return any("512" not in v.upper() and "AMX" not in v.upper() and "DEFAULT" not in v.upper()
               for v in isa_limits().values())


def isa_flags() -> list[str]:
    """The instruction-set flags that matter here: as this CPU reports them, less the
    AVX-512 and AMX ones when the environment caps the kernels at AVX2."""
    flags = [f for f in ISA_FLAGS if f in cpu_model_and_flags()[1]]
    if _limited_to_avx2():
        flags = [f for f in flags if f in ("avx2", "fma")]
    return flags


def _cache_path(name: str = "kernels.json") -> Path:
    root = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(root) / "pusher-rl" / name


def machine_key(*what) -> str:
    """A cache key for a measurement on this machine: the CPU model and flags, the torch
    build, and ``what`` was measured."""
    import torch  # the key names the torch build: its kernels are what was measured

    model, flags = cpu_model_and_flags()
    text = f"{CACHE_VERSION}|{model}|{sorted(flags)}|{torch.__version__}|{torch.__config__.show()}|" + "|".join(map(str, what))
    if isa_limits():  # kernels capped by the environment measure differently
        text += f"|{sorted(isa_limits().items())}"
    return hashlib.sha256(text.encode()).hexdigest()[:24]


def read_cache(name: str = "kernels.json") -> dict:
    """The measurements cached in ``~/.cache/pusher-rl/NAME`` ({} when none)."""
    try:
        return json.loads(_cache_path(name).read_text())
    except (OSError, ValueError):
        return {}


def write_cache(key: str, entry: dict, name: str = "kernels.json") -> None:
    """Add ``entry`` under ``key`` to ``~/.cache/pusher-rl/NAME`` (atomically; best effort)."""
    path = _cache_path(name)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        cache = read_cache(name)
        cache[key] = entry
        write_text_atomic(path, json.dumps(cache, indent=1, sort_keys=True))
    except OSError:
        pass  # no cache: the next process measures again


def available_cores() -> int:
    """The cores this process may run on (its CPU affinity)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        return os.cpu_count() or 1
