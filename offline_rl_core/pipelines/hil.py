"""The HIL-SERL corrections loop, driven over ROS: ``offline-rl hil``.

Each round, on a private DDS domain (``rosproc.isolated_ros_env``):

1. serve the current prior: one ``policy`` node for the whole run, watching
   ``DIR/policy.pt`` (hot reload; it is never restarted) (``serve.launch.yaml``);
2. run E episodes in lockstep: ``sim`` (lockstep, training reset seeds) + ``corrections
   corrector`` (scripted expert stand-in for the person) + ``corrections mux`` (one
   command per stamp, tagged policy/human) + ``recorder --passive`` ->
   ``DIR/round_<r>/corrections.db3`` (``corrections.launch.yaml``);
3. retrain with the ``trainer`` node: AWAC on the offline bag(s) plus every
   correction bag so far, warm-started from the served checkpoint (``--init``), with
   correction-run transitions at ``--correction-ratio`` of each batch; the policy's
   last actions before each takeover are kept out of the actor's targets
   (``learners.data.intervention_actor_mask``);
4. publish: ``DIR/round_<r>/train/policy.pt`` replaces ``DIR/policy.pt`` atomically,
   and the loop waits until the policy node reports the reload.

Every node is given the task (``--task``, else the one the bags record, else pusher_reach;
any task a sim hosts). Success without intervention is measured in process (rollouts of
the served checkpoint on the task's held-out reset seeds, in its own env).
``DIR/summary.json`` and ``DIR/rounds.png`` summarise the rounds. No ROS import here: nodes
are subprocesses, stopped by pid.
"""

from __future__ import annotations

import json
import os
import shutil
import sys
import time
from contextlib import contextmanager
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Callable, Iterator

import numpy as np

from ..common import seeds
from ..common.atomic import atomic_path, write_json_atomic
from ..data.bag import read_transitions
from ..common.errors import UserError
from ..common.interrupts import sigterm_as_interrupt
from ..common.output_paths import remove_if_empty
from ..evaluation.rollouts import evaluate_policy
from ..learners.config import TrainConfig
from ..runs.loggers import DEFAULT_LOGGER, check_logger
from ..serving.checkpoint import load_checkpoint
from ..serving.policy import load_policy, policy_for_task
from ..task.spec import BUILTIN_DIR, DEFAULT_TASK, TaskSpec, load_task
from ros2_shim.ament_index import ros2_run

from .processes import LaunchedProcesses, RosProcess, isolated_ros_env
from ..evaluation.stats import newcombe_diff_ci, wilson_ci
from ..data.transitions import SOURCE_HUMAN, SOURCE_POLICY

DEFAULT_BAG = "bags/mix.db3"
PROJECT_BAG = Path(__file__).resolve().parents[2] / DEFAULT_BAG  # where `make bag` writes it


def default_bag() -> str:
    """bags/mix.db3 of the working directory, else the project's (from anywhere)."""
    return DEFAULT_BAG if Path(DEFAULT_BAG).exists() or not PROJECT_BAG.exists() else str(PROJECT_BAG)


def no_such_bag(bag: str) -> UserError:
    return UserError(f"{bag}: no such bag (in {Path.cwd()}); `make bag` writes {PROJECT_BAG}")
DEMO_PRIOR = "runs/demo/awac/policy.pt"
DEMO_AUTO_PRIOR = "runs/demo/auto/policy.pt"  # make demo's --algo auto prior
EVAL_SEED = seeds.HELD_OUT
TRAIN_SEED_BASE = seeds.ONLINE


@dataclass
class HilConfig:
    out: str = "runs/hil"
    rounds: int = 3
    episodes: int = 30
    prior: str | None = None
    bags: list[str] = field(default_factory=lambda: [DEFAULT_BAG])
    task: str | None = None  # a built-in task or a task file; None: the one the bags record, else pusher_reach
    seed: int = 0
    algo: str = "awac"
    prior_steps: int = TrainConfig.steps
    steps: int = 3000  # retraining steps per round
    correction_ratio: float = 0.5
    # AWAC temperature of the retraining (the prior keeps the chapter's 0.3): sharper
    # advantage weights let the corrections, not the random half of the offline mix, set
    # the actor's targets (in-process trials of this loop, 3 rounds x 30 episodes from the
    # same prior: final - prior +0.12 with beta 0.3, +0.29 with 0.1).
    beta: float = 0.1
    eval_episodes: int = 100
    eval_seed: int = EVAL_SEED
    patience: int = 8
    hold_steps: int = 25
    grace_steps: int = 20
    noise: float = 0.0
    reaction_delay: int = 0
    round_timeout: float = 300.0  # seconds for one round's episodes over ROS

    def validate(self) -> None:
        for name in ("rounds", "episodes", "prior_steps", "steps", "eval_episodes", "patience", "hold_steps"):
            if int(getattr(self, name)) < 1:
                raise UserError(f"--{name.replace('_', '-')} must be >= 1, got {getattr(self, name)}")
        if not 0.0 <= self.correction_ratio <= 1.0:
            raise UserError(f"--correction-ratio must be in [0, 1], got {self.correction_ratio}")
        if self.noise < 0 or self.reaction_delay < 0 or self.grace_steps < 0:
            raise UserError("--noise, --reaction-delay and --grace-steps must be >= 0")
        if self.beta <= 0:
            raise UserError(f"--beta must be > 0, got {self.beta}")
        for bag in self.bags:
            if not Path(bag).exists():
                raise no_such_bag(bag)
        if self.prior is not None and not Path(self.prior).exists():
            raise UserError(f"{self.prior}: no such checkpoint")


class Loop:
    """The processes of one run; every one is stopped by pid, whatever happens."""

    def __init__(self, cfg: HilConfig, log: Callable[[str], None], logger: str = DEFAULT_LOGGER):
        self.cfg = cfg
        self.out = Path(cfg.out)
        self.log = log
        self.logger = logger  # the trainer nodes' --logger
        self.env = isolated_ros_env()
        self.procs: list[RosProcess] = []
        self.task_arg = DEFAULT_TASK  # how the nodes are told the task (task_argument)

    # ------------------------------------------------------------ processes
    def start(self, name: str, cmd: list[str], log_path: Path, ready: str | None = None, timeout: float = 60.0) -> RosProcess:
        proc = RosProcess(cmd, self.env, log_path, name=name)
        self.procs.append(proc)
        proc.start()
        if ready and not proc.wait_for_output(ready, timeout):
            raise UserError(f"{name} did not start (no {ready!r} within {timeout:.0f} s); see {log_path}:\n"
                            + _tail(proc.output()))
        return proc

    def launch(self, file_name: str, arguments: dict, log_dir: Path, ready: dict[str, str] | None = None,
               timeout: float = 60.0) -> LaunchedProcesses:
        """Start the nodes of one of pusher_bringup's launch files, in order, as processes of this loop."""
        launched = LaunchedProcesses.of("pusher_bringup", file_name, arguments, self.env, log_dir)
        self.procs.extend(launched.processes.values())  # stopped by stop_all, whatever happens
        return launched.start(ready=ready, timeout=timeout)

    def stop(self, proc: RosProcess) -> None:
        proc.stop(timeout=5.0)
        if proc in self.procs:
            self.procs.remove(proc)

    def stop_all(self) -> None:
        for proc in reversed(list(self.procs)):
            self.stop(proc)

    def follow(self, proc: RosProcess, timeout: float, show: Callable[[str], str | None],
               give_up: Callable[[], bool] | None = None) -> int | None:
        """Wait for ``proc`` to exit, passing new log lines through ``show`` (progress).
        Returns its exit status, or None when ``give_up()`` said to stop waiting."""
        deadline = time.monotonic() + timeout
        seen = 0
        while True:
            text = proc.output()
            lines = text[seen:].split("\n")
            if lines:
                complete, rest = lines[:-1], lines[-1]
                seen = len(text) - len(rest)
                for line in complete:
                    msg = show(line)
                    if msg:
                        self.log(msg)
            rc = proc.poll()
            if rc is not None:
                return rc
            if give_up is not None and give_up():
                return None
            if time.monotonic() > deadline:
                raise UserError(f"{proc.name} did not finish within {timeout:.0f} s; see {proc.log_path}:\n"
                                + _tail(proc.output()))
            time.sleep(0.2)

    # ------------------------------------------------------------ steps
    def train(self, name: str, bags: list[str], steps: int | None, seed: int, out_dir: Path, init: str | None = None,
              correction_ratio: float | None = None, algo: str | None = None) -> Path:
        """Train with the trainer node; ``steps`` None: as many as ``--algo auto`` plans."""
        args = ["--algo", algo or self.cfg.algo, "--task", self.task_arg, "--seed", seed, "--out", out_dir,
                "--eval-episodes", 0, "--logger", self.logger]
        if steps is not None:
            args += ["--steps", steps, "--log-every", max(100, steps // 8)]
        else:
            args += ["--log-every", 2000]
        for bag in bags:
            args += ["--bag", bag]
        if init:  # a warm start is trained at its own width (an auto prior may be wider than the default)
            args += ["--init", init, "--hidden", int(load_checkpoint(init)["hidden"])]
        if correction_ratio is not None:
            args += ["--correction-ratio", correction_ratio, "--beta", self.cfg.beta]
        proc = self.start(f"trainer ({name})", ros2_run("trainer", "node", *args), out_dir.parent / f"{out_dir.name}.log")
        started = time.monotonic()
        rc = self.follow(proc, 3600.0, lambda line: f"    {name}: {line.strip()}" if line.strip().startswith("step") else None)
        self.stop(proc)
        if rc != 0 or not (out_dir / "policy.pt").is_file():
            raise UserError(f"the trainer node failed (exit {rc}); see {proc.log_path}:\n" + _tail(proc.output()))
        self.log(f"    {name}: trained in {time.monotonic() - started:.0f} s -> {out_dir / 'policy.pt'}")
        return out_dir / "policy.pt"

    def corrections_round(self, r: int, round_dir: Path) -> dict:
        cfg = self.cfg
        bag = round_dir / "corrections.db3"
        reset_seed = TRAIN_SEED_BASE + 10000 * cfg.seed + (r - 1) * cfg.episodes
        # mux, corrector, recorder, then the sim, which holds its first state until the
        # recorder is matched (corrections.launch.yaml; the policy node already serves)
        launched = self.launch("corrections.launch.yaml", {
            "with_policy": "false", "task": self.task_arg, "out": bag, "episodes": cfg.episodes, "seed": reset_seed,
            "summary": round_dir / "sim.json", "patience": cfg.patience, "hold_steps": cfg.hold_steps,
            "grace_steps": cfg.grace_steps, "noise": float(cfg.noise), "reaction_delay": cfg.reaction_delay,
            "corrector_seed": 1000 * cfg.seed + r,
        }, round_dir, ready={"mux": "mux lockstep", "corrector": "answering", "recorder": "recording"})
        mux, corrector, recorder, sim = (launched[n] for n in ("mux", "corrector", "recorder", "sim"))
        started = time.monotonic()

        def show(line: str) -> str | None:
            if line.startswith("recorder:") and "episodes," in line:
                return f"    round {r}: {line.split(':', 1)[1].strip()}"
            return None

        sim_done: list[float] = []

        def sim_finished_long_ago() -> bool:
            # the sim ran all its episodes; a recorder still waiting has missed some end
            if sim.poll() is not None and not sim_done:
                sim_done.append(time.monotonic())
            return bool(sim_done) and time.monotonic() - sim_done[0] > 15.0

        rc = self.follow(recorder, cfg.round_timeout, show, give_up=sim_finished_long_ago)
        elapsed = time.monotonic() - started
        if rc is None:
            self.log(f"    round {r}: warning: the sim finished but the recorder missed transitions; closing the bag")
            rc = recorder.stop(timeout=10.0)
        try:
            sim.wait(timeout=10.0)
        except Exception:  # noqa: BLE001 - stopped below either way
            pass
        for proc in (sim, corrector, mux):
            self.stop(proc)
        self.stop(recorder)
        if rc != 0 or not bag.exists():
            raise UserError(f"the recorder failed (exit {rc}); see {recorder.log_path}:\n" + _tail(recorder.output()))
        data = read_transitions(bag)
        human = int(np.sum(data.source == SOURCE_HUMAN))
        policy = int(np.sum(data.source == SOURCE_POLICY))
        episodes = np.unique(data.episode)
        run_success = float(np.mean([data.success[data.episode == e].any() for e in episodes])) if len(episodes) else 0.0
        takeovers = int(np.sum((data.source[1:] == SOURCE_HUMAN) & (data.source[:-1] != SOURCE_HUMAN)
                               & (data.episode[1:] == data.episode[:-1])))
        return {
            "bag": str(bag),
            "episodes": int(len(episodes)),
            "transitions": int(len(data)),
            "correction_transitions": human,
            "policy_transitions": policy,
            "intervention_rate": round(human / max(len(data), 1), 6),
            "takeovers": takeovers,
            "success_with_corrections": round(run_success, 6),
            "reset_seeds": [reset_seed, reset_seed + cfg.episodes - 1],
            "ros_seconds": round(elapsed, 1),
        }

    def publish(self, policy_node: RosProcess, checkpoint: Path, served: Path, reloads: int) -> None:
        """Replace the served checkpoint atomically; wait for the policy node's reload."""
        with atomic_path(served) as tmp:
            shutil.copyfile(checkpoint, tmp)
        deadline = time.monotonic() + 30.0
        while time.monotonic() < deadline:
            if policy_node.output().count("reloaded ") >= reloads:
                return
            if not policy_node.running():
                break
            time.sleep(0.1)
        raise UserError(f"the policy node did not reload {served}; see {policy_node.log_path}:\n" + _tail(policy_node.output()))


def resolve_task(loop: Loop, cfg, out: Path) -> TaskSpec:
    """The task of a HIL run (``cfg``: its HilConfig or OnlineHilConfig): ``--task``, else the
    bags' (``offline-rl train``'s rule); a given prior must be of it, and a sim must host it
    (the arm of the run, and the held-out rollouts it is scored on). Sets how the nodes are
    told it (``loop.task_arg``); for a task other than pusher_reach, ``cfg.task`` too, so every
    later step and the summary's config name what the nodes were told."""
    from ..runs.training_run import task_of_run

    task = task_of_run(cfg.bags, cfg.task)
    if cfg.prior:
        policy_for_task(load_checkpoint(cfg.prior), cfg.prior, task)  # a prior of another task: one line naming both
    if not task.sim:
        raise UserError(f"task {task.name} ({task.source_file()}): offline-rl hil runs the task in a sim and scores "
                        "it on held-out rollouts there; the task has no sim section")
    loop.task_arg = task_argument(task, out)
    if task.digest != load_task(DEFAULT_TASK).digest:
        cfg.task = loop.task_arg
    return task


def task_argument(task: TaskSpec, out: Path) -> str:
    """What a node's ``task`` parameter is given for ``task``: a built-in's name, the task
    file it was read from, or (a task only a bag records) its spec written to OUT/task.yaml."""
    if task.path is not None and task.path.parent == BUILTIN_DIR and task.digest == load_task(task.name).digest:
        return task.name
    if task.path is not None and task.path.is_file() and load_task(task.path).digest == task.digest:
        return str(task.path)
    path = out / "task.yaml"
    write_json_atomic(path, task.describe())  # JSON is YAML
    return str(path)


def _tail(text: str, lines: int = 15) -> str:
    return "\n".join(text.rstrip().splitlines()[-lines:])


def reusable_prior(path: str | os.PathLike, bags: list[str], cfg: HilConfig, seed: int | None = None) -> bool:
    """True when ``path`` is an AWAC checkpoint trained for ``prior_steps`` on exactly
    ``bags`` (and with ``seed``, when given)."""
    try:
        ckpt = load_checkpoint(path)
    except Exception:  # noqa: BLE001 - not reusable, whatever is wrong
        return False
    cfgd = ckpt.get("config") or {}
    if ckpt.get("algorithm") != cfg.algo or int(cfgd.get("steps", -1)) != cfg.prior_steps or cfgd.get("init"):
        return False
    if (ckpt.get("metrics") or {}).get("init"):
        return False
    if seed is not None and int(ckpt.get("seed", -1)) != int(seed):
        return False
    return _trained_on(ckpt, bags)


def _trained_on(ckpt: dict, bags: list[str]) -> bool:
    """Whether ``ckpt`` was trained on exactly the transitions of ``bags``."""
    from ..runs.training_run import load_bags

    data, _ = load_bags(bags)
    return ckpt.get("dataset_hash") == data.content_hash()


def reusable_auto_prior(path: Path, bags: list[str], seed: int) -> bool:
    """True when ``path`` was trained by ``--algo auto`` (its default budget) on exactly
    ``bags`` with ``seed``: its metrics.json holds the plan."""
    try:
        ckpt = load_checkpoint(path)
        metrics = json.loads((path.parent / "metrics.json").read_text())
    except Exception:  # noqa: BLE001 - not reusable, whatever is wrong
        return False
    from ..runs.prior import DEFAULT_BUDGET_FROM

    plan = metrics.get("plan") or {}
    if plan.get("choice") != ckpt.get("algorithm") or plan.get("budget_from") != DEFAULT_BUDGET_FROM:
        return False
    if int(ckpt.get("seed", -1)) != int(seed) or (ckpt.get("config") or {}).get("init") or metrics.get("init"):
        return False
    return _trained_on(ckpt, bags)


def resolve_prior(loop: Loop, given: str | None, bags: list[str], seed: int, prior_steps: int, out: Path,
                  log: Callable[[str], None], algo: str = "awac") -> tuple[Path, str]:
    """(the prior checkpoint, how it was had: given / reused / trained). ``algo`` awac: the
    chapter's AWAC prior, ``make demo``'s or an earlier run's when it was trained so on these
    bags; auto: ``offline-rl train --algo auto``'s (README, "The best prior"), ``make demo``'s
    or an earlier run's when it was trained so. Otherwise trained now with the trainer node."""
    if given:
        return Path(given), "given"
    if algo == "auto":
        for candidate in (Path(DEMO_AUTO_PRIOR), out / "prior" / "policy.pt"):
            if candidate.exists() and reusable_auto_prior(candidate, bags, seed):
                log(f"prior: reusing {candidate} (--algo auto, same data and seed)")
                return candidate, "reused"
        log(f"prior: training --algo auto on {', '.join(bags)}, seed {seed} (trainer node)")
        return loop.train("prior", bags, None, seed, out / "prior", algo="auto"), "trained"
    spec = HilConfig(prior_steps=prior_steps, algo="awac")
    for candidate in (Path(DEMO_PRIOR), out / "prior" / "policy.pt"):
        if candidate.exists() and reusable_prior(candidate, bags, spec, seed):
            log(f"prior: reusing {candidate} (AWAC, {prior_steps} steps, same data and seed)")
            return candidate, "reused"
    log(f"prior: training AWAC on {', '.join(bags)} for {prior_steps} steps, seed {seed} (trainer node)")
    return loop.train("prior", bags, prior_steps, seed, out / "prior", algo="awac"), "trained"


def evaluate(path: Path, cfg: HilConfig, task: TaskSpec) -> dict:
    """The served checkpoint without intervention, on ``task``'s held-out resets in its own env."""
    return evaluate_policy(load_policy(path, task), cfg.eval_episodes, cfg.eval_seed, task=task)


def plot_rounds(rows: list[dict], final: dict, path: Path) -> None:
    from ..runs.plots import _save_atomic, plt

    fig, ax = plt.subplots(figsize=(6.4, 4.0))
    r = [row["round"] for row in rows]
    succ = [row["success_without_intervention"] for row in rows] + [final["success_rate"]]
    ax.plot(r + [r[-1] + 1], succ, "o-", label="success without intervention (served policy)")
    ax.plot(r, [row["intervention_rate"] for row in rows], "s--", label="intervention rate (share of steps)")
    ax.set_xlabel("round (served policy) / final policy")
    ax.set_ylim(0, 1)
    ax.set_xticks(r + [r[-1] + 1], [str(x) for x in r] + ["final"])
    ax.grid(alpha=0.3)
    ax.legend(loc="best", fontsize=8)
    ax.set_title("HIL corrections loop")
    _save_atomic(fig, path)


def run_hil(cfg: HilConfig, log: Callable[[str], None] = lambda s: print(s, file=sys.stderr, flush=True),
            logger: str = DEFAULT_LOGGER) -> dict:
    cfg.validate()
    out = Path(cfg.out)
    t0 = time.monotonic()
    check_logger(logger)
    loop = Loop(cfg, log, logger)
    with hil_session(out, loop):
        log(f"hil: {cfg.rounds} rounds x {cfg.episodes} episodes -> {out} (ROS_DOMAIN_ID {loop.env['ROS_DOMAIN_ID']})")
        task = resolve_task(loop, cfg, out)
        prior_path, prior_from = resolve_prior(loop, cfg.prior, cfg.bags, cfg.seed, cfg.prior_steps, out, log)
        served = out / "policy.pt"
        with atomic_path(served) as tmp:
            shutil.copyfile(prior_path, tmp)

        # the mux drives the arm, never the policy directly: a task's sim takes its controller's
        # topic too, where the policy's own command would answer a state before the corrector heard it
        policy_node = loop.launch("serve.launch.yaml", {"checkpoint": served, "task": loop.task_arg, "poll_period": 0.2,
                                                        "closed_loop": "false", "publish_command": "false"},
                                  out, ready={"policy": "serving"})["policy"]
        rows: list[dict] = []
        correction_bags: list[str] = []
        prior_eval = None
        for r in range(1, cfg.rounds + 1):
            round_dir = out / f"round_{r}"
            round_dir.mkdir(parents=True, exist_ok=True)
            ev = evaluate(served, cfg, task)
            if prior_eval is None:
                prior_eval = ev
            log(f"round {r}/{cfg.rounds}: served policy succeeds {ev['successes']}/{ev['episodes']} without "
                f"intervention; running {cfg.episodes} corrected episodes over ROS")
            stats = loop.corrections_round(r, round_dir)
            correction_bags.append(stats["bag"])
            log(f"round {r}/{cfg.rounds}: intervention rate {stats['intervention_rate']:.3f} "
                f"({stats['correction_transitions']} corrections, {stats['takeovers']} takeovers, "
                f"{stats['transitions']} transitions, {stats['ros_seconds']:.0f} s); retraining")
            ckpt = loop.train(f"round {r}", cfg.bags + correction_bags, cfg.steps, cfg.seed + r, round_dir / "train",
                              init=str(served), correction_ratio=cfg.correction_ratio)
            loop.publish(policy_node, ckpt, served, reloads=r)
            log(f"round {r}/{cfg.rounds}: policy node reloaded {served}")
            rows.append({"round": r, "success_without_intervention": ev["success_rate"],
                         "successes": ev["successes"], **stats, "checkpoint": str(ckpt)})
        final_eval = evaluate(served, cfg, task)
        loop.stop_all()

        n = cfg.eval_episodes
        lo, hi = newcombe_diff_ci(final_eval["successes"], n, prior_eval["successes"], n)
        summary = {
            "rounds": rows,
            "prior": str(prior_path),
            "prior_from": prior_from,
            "prior_success": prior_eval["success_rate"],
            "prior_ci": [round(v, 6) for v in wilson_ci(prior_eval["successes"], n)],
            "final_success": final_eval["success_rate"],
            "final_ci": [round(v, 6) for v in wilson_ci(final_eval["successes"], n)],
            "diff": round(final_eval["success_rate"] - prior_eval["success_rate"], 6),
            "diff_ci_lo": round(lo, 6),
            "diff_ci_hi": round(hi, 6),
            "diff_significant": bool(lo > 0 or hi < 0),
            "intervention_rate_first": rows[0]["intervention_rate"],
            "intervention_rate_last": rows[-1]["intervention_rate"],
            "eval_episodes": n,
            "eval_seed": cfg.eval_seed,
            "final_checkpoint": str(served),
            "config": asdict(cfg),
            "wall_seconds": round(time.monotonic() - t0, 1),
        }
        write_json_atomic(out / "summary.json", summary)
        plot_rounds(rows, final_eval, out / "rounds.png")
        log(f"hil: prior {prior_eval['successes']}/{n} -> final {final_eval['successes']}/{n}, difference "
            f"{summary['diff']:+.2f} [{lo:+.3f}, {hi:+.3f}]{' (excludes 0)' if summary['diff_significant'] else ''}; "
            f"intervention rate {rows[0]['intervention_rate']:.3f} -> {rows[-1]['intervention_rate']:.3f}; "
            f"{summary['wall_seconds']:.0f} s; wrote {out / 'summary.json'} and {out / 'rounds.png'}")
        return summary


@contextmanager
def hil_session(out: Path, loop: "Loop") -> Iterator[None]:
    """What every HIL run shares around its work: SIGTERM stops it as Ctrl-C does, every
    process ``loop`` started is stopped by its pid, and a run that fails before writing
    anything leaves no output directory behind."""
    created = not out.exists()
    out.mkdir(parents=True, exist_ok=True)
    with sigterm_as_interrupt():
        try:
            yield
        except BaseException:
            remove_if_empty(out, created)
            raise
        finally:
            loop.stop_all()
