"""Which kernels the MLP's hidden layer runs on this CPU: chosen by measuring, once.

Nearly all of a training step's arithmetic is the hidden layer's three products
(forward, weight gradient, input gradient). Which library and precision runs them
fastest differs between CPUs in ways flags alone do not predict: MKL runs only its AVX2
kernels on AMD CPUs, where oneDNN is faster in fp32; a CPU with AVX512-BF16 can still
run oneDNN's bf16 products slower than fp32; without native bf16 (AMX or AVX512-BF16)
bf16 is emulated and slower. So each product's candidates are timed
on this machine at the network's size, the fastest kept, and the choice cached per CPU
model, flags, torch build, size and thread count (``~/.cache/pusher-rl/kernels.json``),
so every later run on this machine makes the same choice and stays bit-reproducible.
``make setup`` measures it ahead (``python -m offline_rl_core.fast.kernel_choice``).

bf16 is a candidate only where the CPU has it natively and the run is not
``--deterministic``; it is chosen only when it beats fp32 clearly (``BF16_MARGIN``):
it costs precision, and it trains other bytes than fp32, so a choice that a second
measurement (a new machine of the same kind, a lost cache) could turn the other way
would make the same command give different results.
"""

from __future__ import annotations

import functools
import os
import statistics
import sys
import time
from dataclasses import asdict, dataclass

import torch

from ..common.machine import cpu_model_and_flags, isa_flags, machine_key, read_cache, write_cache

BF16_MARGIN = 1.25


def native_bf16() -> bool:
    return bool({"amx_bf16", "avx512_bf16"} & set(isa_flags()))


@functools.lru_cache(maxsize=1)
def onednn_linear_available() -> bool:
    """True when torch's oneDNN linear (``mkldnn._linear_pointwise``) runs here."""
    try:
        if not torch.backends.mkldnn.is_available():
            return False
        out = torch.ops.mkldnn._linear_pointwise(torch.ones(2, 3), torch.ones(4, 3), None, "none", [], "")
        return bool(torch.equal(out, torch.full((2, 4), 3.0)))
    except (AttributeError, RuntimeError):
        return False


@dataclass(frozen=True)
class Kernels:
    """The hidden layer's dtype and, per product, "onednn" or "blas" (torch's default
    BLAS: ``addmm`` / ``mm``)."""

    dtype: str = "fp32"  # "fp32" | "bf16"
    forward: str = "blas"
    grad_weight: str = "blas"
    grad_input: str = "blas"

    @property
    def torch_dtype(self) -> torch.dtype:
        return torch.bfloat16 if self.dtype == "bf16" else torch.float32

    def describe(self) -> str:
        return f"{self.dtype} (forward {self.forward}, weight grad {self.grad_weight}, input grad {self.grad_input})"


def product(name: str, backend: str):
    """The product ``name`` on ``backend``, as a function of 2-D tensors."""
    linear = torch.ops.mkldnn._linear_pointwise
    if name == "forward":  # relu(x @ w + b)
        if backend == "onednn":
            return lambda x, w, b: linear(x, w.t(), b, "relu", [], "")
        return lambda x, w, b: torch.addmm(b, x, w).relu_()
    if name == "grad_weight":  # x.T @ g
        if backend == "onednn":
            return lambda x, g: linear(x.t(), g.t(), None, "none", [], "")
        return lambda x, g: x.t().mm(g)
    if name == "grad_input":  # g @ w.T
        if backend == "onednn":
            return lambda g, w: linear(g, w, None, "none", [], "")
        return lambda g, w: g.mm(w.t())
    raise ValueError(name)


def _time(fn, args, repeats: int = 7, calls: int = 10) -> float:
    for _ in range(3):
        fn(*args)
    samples = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        for _ in range(calls):
            fn(*args)
        samples.append((time.perf_counter() - t0) / calls)
    return statistics.median(samples)


def measure(hidden: int, batch: int, allow_bf16: bool) -> dict:
    """Time every candidate; returns the choice per dtype and the timings (seconds)."""
    backends = ["blas"] + (["onednn"] if onednn_linear_available() else [])
    dtypes = ["fp32"] + (["bf16"] if allow_bf16 and native_bf16() else [])
    gen = torch.Generator().manual_seed(0)
    x = torch.rand(batch, hidden, generator=gen)
    w = torch.rand(hidden, hidden, generator=gen)
    b = torch.rand(hidden, generator=gen)
    timings: dict[str, dict[str, float]] = {}
    best: dict[str, dict[str, str]] = {}
    totals: dict[str, float] = {}
    for dt in dtypes:
        cast = (lambda t: t.to(torch.bfloat16)) if dt == "bf16" else (lambda t: t)
        xc, wc, bc = cast(x), cast(w), cast(b)
        args = {"forward": (xc, wc, bc), "grad_weight": (xc, xc), "grad_input": (xc, wc)}
        best[dt], totals[dt] = {}, 0.0
        for name, a in args.items():
            for backend in backends:
                timings[f"{dt}/{name}/{backend}"] = _time(product(name, backend), a)
            pick = min(backends, key=lambda be: timings[f"{dt}/{name}/{be}"])
            best[dt][name] = pick
            totals[dt] += timings[f"{dt}/{name}/{pick}"]
    return {"best": best, "totals": totals, "timings": timings}


def _cache_key(hidden: int, batch: int, threads: int, deterministic: bool) -> str:
    return machine_key(f"{hidden}x{batch}", f"threads={threads}", f"deterministic={deterministic}")


def choose(deterministic: bool, hidden: int = 256, batch: int = 256, threads: int = 1) -> Kernels:
    """The hidden layer's kernels for a run (cached on disk after the first measurement).

    ``PUSHER_RL_KERNELS`` overrides: ``fp32`` or ``bf16`` (then each product's fastest
    backend), or ``DTYPE-BACKEND`` (e.g. ``fp32-onednn``, ``fp32-blas``) for all three."""
    forced = os.environ.get("PUSHER_RL_KERNELS", "").strip().lower()
    if forced:
        return _forced(forced, hidden, batch, deterministic)
    return _measured(deterministic, hidden, batch, threads)


@functools.lru_cache(maxsize=None)
def _measured(deterministic: bool, hidden: int, batch: int, threads: int) -> Kernels:
    key = _cache_key(hidden, batch, threads, deterministic)
    entry = read_cache().get(key)
    if entry is None:
        previous = torch.get_num_threads()
        torch.set_num_threads(threads)
        try:
            result = measure(hidden, batch, allow_bf16=not deterministic)
        finally:
            torch.set_num_threads(previous)
        totals = result["totals"]
        dtype = "bf16" if "bf16" in totals and totals["fp32"] > BF16_MARGIN * totals["bf16"] else "fp32"
        entry = {"dtype": dtype, **result["best"][dtype], "totals_us": {k: round(v * 1e6, 1) for k, v in totals.items()},
                 "measured": time.strftime("%Y-%m-%dT%H:%M:%S"), "cpu": cpu_model_and_flags()[0], "isa": isa_flags()}
        write_cache(key, entry)
    return Kernels(entry["dtype"], entry["forward"], entry["grad_weight"], entry["grad_input"])


@functools.lru_cache(maxsize=None)
def _forced(spec: str, hidden: int, batch: int, deterministic: bool) -> Kernels:
    from ..common.errors import UserError

    dtype, _, backend = spec.partition("-")
    if dtype not in ("fp32", "bf16") or backend not in ("", "blas", "onednn"):
        raise UserError(f"PUSHER_RL_KERNELS={spec}: expected fp32 or bf16, optionally with -blas or -onednn")
    if dtype == "bf16" and deterministic:
        raise UserError("PUSHER_RL_KERNELS=bf16 contradicts --deterministic (fp32 everywhere)")
    if backend == "onednn" and not onednn_linear_available():
        raise UserError("PUSHER_RL_KERNELS: torch's oneDNN linear is not available here")
    if backend:
        return Kernels(dtype, backend, backend, backend)
    best = measure(hidden, batch, allow_bf16=dtype == "bf16")["best"][dtype]
    return Kernels(dtype, **best)


def report() -> dict:
    """What a run on this machine uses, for the bench and ``make setup``."""
    return {"cpu": cpu_model_and_flags()[0], "isa": isa_flags(), "native_bf16": native_bf16(),
            "onednn": onednn_linear_available(),
            "default": asdict(choose(False)), "deterministic": asdict(choose(True))}


def main() -> int:
    t0 = time.perf_counter()
    default, exact = choose(False), choose(True)
    model = cpu_model_and_flags()[0] or "unknown CPU"
    print(f"kernels for {model} [{' '.join(isa_flags())}] ({time.perf_counter() - t0:.1f} s): "
          f"default {default.describe()}; --deterministic {exact.describe()}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
