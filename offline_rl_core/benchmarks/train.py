"""Training figures: gradient steps/s against the chapter's loop and d3rlpy, the
three-seed ensemble, and the chapter experiment's wall time.

"Ours" is ``train_seeds`` timed from its own progress clock (the loop, without the
one-off setup that the references do not have either). On the CPU two modes are
timed: ``default`` (the kernels ``kernel_choice`` measured fastest here) and
``deterministic`` (fp32 everywhere). With ``--device cuda`` every contender trains on the GPU, and ours is
timed as plain eager steps (``cuda``) and as a replayed CUDA graph (``cuda_graph``,
the default there); the experiment figure, whose evaluation is CPU MuJoCo, is CPU-only.
"""

from __future__ import annotations

import tempfile
import time

import torch

from ..data.collect import collect_transitions
from ..learners import TrainConfig, stepper, train_seeds
from ..learners.loop import torch_threads
from ..fast import kernel_choice
from . import d3rlpy_ref
from ..runs import chapter_loop as chapter
from .harness import BenchSettings, figure, interleave, median, pending


def ours_rate(data, algo: str, steps: int, s: BenchSettings, deterministic: bool, seeds=(0,),
              cuda_graph: bool = True) -> float:
    """Gradient steps per second of ``train_seeds`` (all members step together)."""
    last = {}

    def progress(p):
        last["elapsed"] = p.elapsed_s

    # as `offline-rl train` runs by default (or on the bench's --threads)
    cfg = TrainConfig(algo=algo, steps=steps, batch_size=s.batch_size, hidden=s.hidden, log_every=max(1, steps),
                      deterministic=deterministic, threads=s.threads, device=s.device, cuda_graph=cuda_graph)
    results = train_seeds(data, cfg, list(seeds), progress=progress)
    THREADS_USED[algo] = results[0].checkpoint.get("train_threads")
    return steps / last["elapsed"]


THREADS_USED: dict[str, int | None] = {}  # per learner, the threads our last timed run's step used


_PRODUCTS = {"aten::addmm", "aten::mm", "aten::bmm", "aten::baddbmm", "mkldnn::_linear_pointwise"}


def _kind_of_call(name: str) -> str:
    op = name.split(".")[0]
    if op in _PRODUCTS:
        return "products"
    if "adam" in op or op.startswith("aten::_foreach"):
        return "optimiser"
    return "other"


def step_work_and_chain(data, algo: str, s: BenchSettings, repeats: int = 5) -> tuple[float, float, dict] | None:
    """(microseconds of work in one replayed step, its longest chain of calls that must
    run one after another, the work by kind of call), as the C++ replay times them call
    by call (medians over ``repeats`` recordings); None where the replay is not built.
    With n threads a step takes at least max(work / n, chain): the ceiling of any
    schedule on this CPU."""
    from ..fast import graph_runner
    from ..learners.data import MemberData
    from ..learners.loop import LEARNERS, seed_generators

    if graph_runner.unavailable_reason() is not None or on_gpu(s):
        return None
    cfg = TrainConfig(algo=algo, batch_size=s.batch_size, hidden=s.hidden)
    idx = torch.randint(0, len(data), (1, s.batch_size), generator=torch.Generator().manual_seed(0))
    work, chain, kinds = [], [], []
    with torch_threads(1):
        for _ in range(repeats):
            learner = LEARNERS[algo](cfg, 1, [seed_generators(0)[0]], data.obs.shape[1], data.action.shape[1])
            step = stepper.make_step(learner.update, MemberData([data]), (1, s.batch_size), "cpu", True, threads=2)
            for _ in range(32):  # eager, recorded, then replayed until timed call by call
                step(idx)
                if step.kind == "cpp" and step.replay.program.measured:
                    break
            if step.kind != "cpp" or not step.replay.program.measured:
                return None
            w, c = step.replay.program.measured_us()
            work.append(w)
            chain.append(c)
            by_kind = {"products": 0.0, "optimiser": 0.0, "other": 0.0}
            for name, us in step.replay.program.call_times_us():
                by_kind[_kind_of_call(name)] += us
            kinds.append(by_kind)
    return median(work), median(chain), {k: round(median([d[k] for d in kinds]), 1) for k in kinds[0]}


def chapter_rate(tensors, algo: str, steps: int, s: BenchSettings) -> float:
    cs = chapter.ChapterSettings(steps=steps, batch_size=s.batch_size, hidden=s.hidden)
    return chapter.steps_per_second(algo, tensors, cs)


def _modes(s: BenchSettings) -> list[tuple[str, dict]]:
    """(label, ``ours_rate`` options) of the modes worth timing on this device."""
    if on_gpu(s):
        return [("cuda", {"deterministic": True, "cuda_graph": False}),
                ("cuda_graph", {"deterministic": True, "cuda_graph": True})]
    # the default (kernels chosen by measuring on this CPU; bf16 only where it won) and
    # --deterministic (fp32 everywhere)
    return [("default", {"deterministic": False}), ("deterministic", {"deterministic": True})]


def on_gpu(s: BenchSettings) -> bool:
    return torch.device(s.device).type == "cuda"


def run(s: BenchSettings, log=print) -> list:
    figs = []
    data = collect_transitions(s.episodes, 0.3, 0)
    tensors = chapter.dataset_tensors(data, s.device)
    d3_version = d3rlpy_ref.available()
    d3_note = "" if d3_version else "d3rlpy not installed (pip install -e '.[bench]'); d3rlpy rows skipped"
    # a GPU step is ~10x shorter: time more of them, so set-up and capture stay small
    n = s.train_steps * (2 if on_gpu(s) else 1)
    where = f" on {torch.cuda.get_device_name(torch.device(s.device))}" if on_gpu(s) else ""
    warm = max(2, min(20, n // 10))

    threads = torch.get_num_threads()
    # the references as a user runs them (torch's default threads) and on one thread:
    # the faster of the two is the reference
    ref_threads = [threads] + ([1] if threads > 1 and not on_gpu(s) else [])

    def at_threads(fn, t):
        def timed():
            with torch_threads(t):
                return fn()
        return timed

    for algo in ("awac", "bc"):
        steps = n if algo == "awac" else 3 * n  # BC steps are ~5x cheaper: time a similar span
        contenders = {f"chapter_{t}t": at_threads(lambda a=algo, k=steps: chapter_rate(tensors, a, k, s), t)
                      for t in ref_threads}
        for label, opts in _modes(s):
            contenders[f"ours_{label}"] = lambda a=algo, k=steps, o=opts: ours_rate(data, a, k, s, **o)
        if d3_version:
            trainer = d3rlpy_ref.D3rlpyTrainer(algo, data, s.hidden, s.batch_size, device=s.device)
            trainer.run(warm)
            for t in ref_threads:
                contenders[f"d3rlpy_{t}t"] = at_threads(lambda tr=trainer, k=steps: k / tr.run(k), t)
        # warm-up: first calls pay for allocator and oneDNN kernel set-up
        chapter_rate(tensors, algo, warm, s)
        for label, opts in _modes(s):
            ours_rate(data, algo, warm, s, **opts)
        rates = {k: median(v) for k, v in interleave(contenders, s.train_repeats).items()}
        log(f"  {algo} steps/s: " + ", ".join(f"{k} {v:.1f}" for k, v in rates.items()))

        def best(name):
            t = max(ref_threads, key=lambda t: rates[f"{name}_{t}t"])
            others = ", ".join(f"{u} thread(s) {rates[f'{name}_{u}t']:.1f}" for u in ref_threads)
            return rates[f"{name}_{t}t"], f"{t} torch thread(s), the faster of {others} steps/s"

        chapter_ref, chapter_how = best("chapter")
        bound = step_work_and_chain(data, algo, s) if algo == "awac" else None
        if bound is not None:
            work, chain, by_kind = bound
            n_threads = stepper.step_threads(s.threads)
            ceiling = 1e6 / max(work / n_threads, chain)
            figs.append(figure("train", "awac_steps_per_s_ceiling_vs_chapter", "steps/s", ceiling, chapter_ref,
                               "chapter loop", target_text="(info: the most any schedule of our step gets here)",
                               note=f"one step is {work:.0f} us of calls, {chain:.0f} us of them one after another; "
                                    f"on {n_threads} thread(s) at least max(work/{n_threads}, chain); the work: "
                                    + ", ".join(f"{k} {v:.0f} us" for k, v in by_kind.items()),
                               extra={"work_us": round(work, 1), "chain_us": round(chain, 1), "threads": n_threads,
                                      "work_by_kind_us": by_kind}))
        for label, _ in _modes(s):
            ours = rates[f"ours_{label}"]
            step_threads = THREADS_USED.get(algo)
            kernels = kernel_choice.choose(label == "deterministic", s.hidden, s.batch_size,
                                           stepper.intra_op_threads(s.threads)).describe() if not on_gpu(s) else s.device
            note = f"kernels: {kernels}; ours: the step on {step_threads} thread(s); chapter: {chapter_how}"
            if algo == "awac":
                figs.append(figure("train", f"awac_steps_per_s_{label}_vs_chapter", "steps/s", ours, chapter_ref,
                                   f"chapter loop{where}", target=lambda o, r, x: x >= 3.0, target_text=">= 3x",
                                   note=note))
            else:
                figs.append(figure("train", f"bc_steps_per_s_{label}_vs_chapter", "steps/s", ours, chapter_ref,
                                   f"chapter loop{where}", target_text="(info)", note=note))
            want = 4.0 if algo == "awac" else 3.0
            if d3_version:
                d3_ref, d3_how = best("d3rlpy")
                figs.append(figure("train", f"{algo}_steps_per_s_{label}_vs_d3rlpy", "steps/s", ours, d3_ref,
                                   f"d3rlpy {d3_version} {algo.upper()}{where}", target=lambda o, r, x, w=want: x >= w,
                                   target_text=f">= {want:g}x", note=f"d3rlpy: {d3_how}"))
            else:
                figs.append(pending("train", f"{algo}_steps_per_s_{label}_vs_d3rlpy", "steps/s", "d3rlpy", d3_note,
                                    f">= {want:g}x", status="skipped"))

    # Three seeds as one stacked ensemble, against three single-seed runs one after another.
    k = max(2, n // 2)
    members = len(s.experiment_seeds)
    label, opts = _modes(s)[-1] if on_gpu(s) else _modes(s)[0]
    got = interleave({
        "single": lambda: ours_rate(data, "awac", k, s, **opts),
        "stacked": lambda: ours_rate(data, "awac", k, s, seeds=s.experiment_seeds, **opts),
    }, s.train_repeats)
    single, stacked = median(got["single"]), median(got["stacked"]) * members
    figs.append(figure("train", f"awac_{members}seed_ensemble_member_steps_per_s", "member-steps/s", stacked, single,
                       f"one seed at a time (ours, {label}{where})", target_text="(info)"))

    if not on_gpu(s):
        figs.extend(experiment_figures(s, log))
    return figs


def experiment_figures(s: BenchSettings, log=print) -> list:
    """`offline-rl experiment --seeds ...` wall time against the chapter's script run per seed.

    Ours trains in one worker process per core (the experiment's default). The chapter's
    script runs its seeds one after another; it is timed with this run's torch threads
    and, where that is fewer than the cores, with one intra-op thread per core too, and
    the faster of the two is the reference: both sides get every core."""
    from ..runs.experiment import ExperimentConfig, run_experiment
    from ..learners.loop import torch_threads
    from ..common.machine import available_cores

    figs = []
    seeds = list(s.experiment_seeds)
    cores = available_cores()
    cs = chapter.ChapterSettings(steps=s.experiment_steps, batch_size=s.batch_size, hidden=s.hidden)

    def chapter_runs(threads: int) -> float:
        with torch_threads(threads):
            t0 = time.perf_counter()
            for seed in seeds:
                chapter.run_chapter_experiment(s.episodes, 0.3, seed, cs, *s.experiment_eval)
            return time.perf_counter() - t0

    def ours(deterministic: bool) -> float:
        cfg = ExperimentConfig(seeds=seeds, steps=s.experiment_steps, episodes=s.episodes, batch_size=s.batch_size,
                               hidden=s.hidden, deterministic=deterministic, n_seeds=s.experiment_eval[0],
                               eval_episodes=s.experiment_eval[1], workers=cores)
        with tempfile.TemporaryDirectory(prefix="bench_experiment_") as out:
            t0 = time.perf_counter()
            run_experiment(cfg, out, log=lambda line: None)
            return time.perf_counter() - t0

    threads = torch.get_num_threads()
    contenders = {"chapter": lambda: chapter_runs(threads)}
    if threads < cores:
        contenders[f"chapter_{cores}_threads"] = lambda: chapter_runs(cores)
    for label, opts in _modes(s):
        contenders[f"ours_{label}"] = lambda d=opts["deterministic"]: ours(d)
    times = {k: median(v) for k, v in interleave(contenders, 1).items()}
    log("  experiment wall s: " + ", ".join(f"{k} {v:.1f}" for k, v in times.items()))
    reference = min(v for k, v in times.items() if k.startswith("chapter"))
    for label, _ in _modes(s):
        figs.append(figure("train", f"experiment_{len(seeds)}seeds_wall_s_{label}", "s", times[f"ours_{label}"],
                           reference, f"{len(seeds)} chapter runs", higher_is_better=False,
                           target=lambda o, r, x: x >= 4.0, target_text=">= 4x faster",
                           note=f"{s.experiment_steps} steps, {s.episodes} episodes, "
                                f"{s.experiment_eval[0] * s.experiment_eval[1]} eval episodes per arm and seed; "
                                f"ours: {cores} worker processes, 1 thread each while runs wait, then the freed cores; chapter: the faster of "
                                + ", ".join(f"{k} {v:.1f} s" for k, v in times.items() if k.startswith("chapter"))))
    return figs
