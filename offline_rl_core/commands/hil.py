"""`offline-rl hil`: the human-in-the-loop corrections loop over ROS (scripted corrector)."""

from __future__ import annotations

import json

from ..common.errors import UserError
from ..common.output_paths import check_output_dir
from ..pipelines.hil import EVAL_SEED, HilConfig, default_bag, run_hil
from ..pipelines.hil_online import OnlineHilConfig, run_hil_online
from ..common.seeds import seed_arg
from ..task.corrector import STEERS
from ..runs.loggers import DEFAULT_LOGGER, LOGGERS


# Flags of one mode only: their defaults are filled in by mode, so that one given to the
# other mode is refused instead of silently ignored.
OFFLINE_ONLY = ("rounds", "episodes", "steps", "correction_ratio", "beta", "noise", "reaction_delay")
BOTH_MODES = ("patience", "hold_steps", "grace_steps")  # the scripted corrector's, in either mode
ONLINE_ONLY = ("env_steps", "corrector", "mode", "prior_algo", "no_prior", "no_explore", "action_labels", "utd",
               "publish_every",
               "eval_every", "in_process", "from_topics", "success", "end_on_success", "actors", "imitate_expert",
               "critic_warmup", "normalize_obs", "bc_weight", "lr_decay", "steer", "offline_ratio", "corrector_noise")


def _resolve_mode_flags(args) -> None:
    ours, theirs, defaults = ((ONLINE_ONLY, OFFLINE_ONLY, OnlineHilConfig()) if args.online
                              else (OFFLINE_ONLY, ONLINE_ONLY, HilConfig()))
    given = [name for name in theirs if getattr(args, name) is not None]
    if given:
        flags = ", ".join("--" + name.replace("_", "-") for name in given)
        raise UserError(f"{flags}: only with{'out' if args.online else ''} --online; "
                        f"{'the online stage' if args.online else 'the offline rounds'} do not use it")
    for name in ours + BOTH_MODES:
        if getattr(args, name) is None:
            setattr(args, name, getattr(defaults, name))
    if args.out is None:
        args.out = defaults.out
    args.bag = args.bag or [default_bag()]
    check_output_dir(args.out, "--out")


def _run(args) -> int:
    _resolve_mode_flags(args)
    if args.online:
        return _run_online(args)
    cfg = HilConfig(
        out=args.out, rounds=args.rounds, episodes=args.episodes, prior=args.prior, bags=args.bag, task=args.task,
        seed=args.seed, prior_steps=args.prior_steps, steps=args.steps, correction_ratio=args.correction_ratio,
        eval_episodes=args.eval_episodes, eval_seed=args.eval_seed, patience=args.patience,
        hold_steps=args.hold_steps, grace_steps=args.grace_steps, beta=args.beta, noise=args.noise, reaction_delay=args.reaction_delay,
    )
    summary = run_hil(cfg, logger=args.logger)
    print(json.dumps({k: summary[k] for k in ("prior_success", "final_success", "diff_ci_lo", "diff_ci_hi",
                                              "intervention_rate_first", "intervention_rate_last", "wall_seconds")}))
    return 0


def _run_online(args) -> int:
    cfg = OnlineHilConfig(
        out=args.out, env_steps=args.env_steps,
        seed=args.seed, prior=args.prior, no_prior=args.no_prior, no_explore=args.no_explore,
        action_labels=args.action_labels,
        prior_steps=args.prior_steps, prior_algo=args.prior_algo,
        bags=args.bag, task=args.task, corrector=args.corrector, steer=args.steer, mode=args.mode, utd=args.utd,
        offline_ratio=args.offline_ratio, corrector_noise=args.corrector_noise, patience=args.patience,
        hold_steps=args.hold_steps, grace_steps=args.grace_steps, publish_every=args.publish_every,
        eval_every=args.eval_every, eval_episodes=args.eval_episodes,
        eval_seed=args.eval_seed, in_process=args.in_process, from_topics=args.from_topics, success=args.success,
        end_on_success=args.end_on_success, actors=args.actors, imitate_expert=args.imitate_expert,
        critic_warmup=args.critic_warmup, normalize_obs=args.normalize_obs, bc_weight=args.bc_weight,
        lr_decay=args.lr_decay)
    summary = run_hil_online(cfg, logger=args.logger)
    print(json.dumps({k: summary[k] for k in ("prior_success", "final_success", "final_ci", "to", "intervention_rate",
                                              "wall_seconds")}))
    return 0


def register(subparsers) -> None:
    d, od = HilConfig(), OnlineHilConfig()
    p = subparsers.add_parser(
        "hil",
        help="HIL-SERL corrections loop over ROS: serve, correct, record, retrain, reload",
        description="Runs ROUNDS rounds: serve the prior (policy node, hot reload), run EPISODES lockstep episodes with "
        "the scripted corrector taking over through the mux, record them (recorder --passive), retrain AWAC from the "
        "served checkpoint on the offline bag plus all corrections (trainer node, --correction-ratio), reload. "
        "Writes DIR/summary.json and DIR/rounds.png. With --online: the HIL-SERL stage itself, the online "
        "learner fine-tuning the prior from the live stream while the policy node acts (DIR/summary.json with the "
        "learning curve, DIR/online.png). The flags of one mode are refused in the other.",
    )
    p.add_argument("--out", default=None, metavar="DIR", help=f"output directory (default: {d.out}; with --online: {od.out})")
    p.add_argument("--prior", metavar="CKPT", help="checkpoint to start from (default: train AWAC on --bag (--online: see --prior-algo), or reuse "
                   "runs/demo/awac/policy.pt when it was trained so)")
    p.add_argument("--bag", action="append", metavar="PATH",
                   help="offline bag(s) of the prior (default: bags/mix.db3 here, else the project's)")
    p.add_argument("--task", metavar="NAME_OR_FILE",
                   help="the task: a built-in task or a task file, given to the sim, policy, corrector, learner and "
                        "trainer (default: the one the bag records, else pusher_reach); the rounds and --online run "
                        "any task with a sim, scored on its held-out resets in its own env")
    p.add_argument("--seed", type=seed_arg, default=d.seed, help="seed of training and of the corrector (default: %(default)s)")
    p.add_argument("--prior-steps", type=int, default=d.prior_steps, help="steps of the prior's training (default: %(default)s)")
    p.add_argument("--eval-episodes", type=int, default=d.eval_episodes,
                   help="held-out rollouts per evaluation (default: %(default)s)")
    p.add_argument("--eval-seed", type=seed_arg, default=EVAL_SEED, help="first held-out reset seed (default: %(default)s)")
    p.add_argument("--logger", choices=LOGGERS, default=DEFAULT_LOGGER,
                   help="where the curves go besides the JSON files: tensorboard (event files: the trainers' in their "
                        "directories; with --online the learning curve in DIR and the learner's losses in DIR/learner), "
                        "wandb (offline unless WANDB_MODE says otherwise), or none (default: %(default)s)")
    r = p.add_argument_group("offline rounds (without --online)")
    r.add_argument("--rounds", type=int, help=f"correction rounds (default: {d.rounds})")
    r.add_argument("--episodes", type=int, help=f"corrected episodes per round (default: {d.episodes})")
    r.add_argument("--steps", type=int, help=f"retraining steps per round (default: {d.steps})")
    r.add_argument("--correction-ratio", type=float,
                   help=f"share of each batch from correction runs (default: {d.correction_ratio})")
    r.add_argument("--beta", type=float, help=f"AWAC temperature of the retraining (default: {d.beta})")
    c = p.add_argument_group("scripted corrector (--patience, --hold-steps and --grace-steps also online; count the "
                             "task's steps)")
    c.add_argument("--patience", type=int, help=f"k: steps without progress before a takeover (default: {d.patience})")
    c.add_argument("--hold-steps", type=int, help=f"m: steps before handing back; a takeover also ends with its "
                   f"episode (default: {d.hold_steps})")
    c.add_argument("--grace-steps", type=int,
                   help=f"states at an episode's start before progress is judged (default: {d.grace_steps})")
    c.add_argument("--noise", type=float, help=f"std of noise on the corrections (default: {d.noise})")
    c.add_argument("--reaction-delay", type=int, help=f"steps of reaction delay (default: {d.reaction_delay})")
    o = p.add_argument_group("online stage (--online)")
    o.add_argument("--online", action="store_true", help="run the online learner instead of offline rounds "
                   f"(default output directory: {od.out})")
    o.add_argument("--env-steps", type=int, help=f"environment steps of the session "
                   f"(default: {od.env_steps}, 400 s of robot time at 50 Hz)")
    o.add_argument("--corrector", choices=("scripted", "keyboard", "none"),
                   help="who takes over: the scripted stand-in, a person at this terminal (realtime), or nobody "
                        f"(default: {od.corrector})")
    o.add_argument("--steer", choices=STEERS,
                   help="how the scripted corrector takes over: expert (the task's scripted expert) or stick (the "
                        "fingertip steered straight at the goal, as a person with a Cartesian stick or SpaceMouse "
                        f"does; reach tasks) (default: {od.steer})")
    o.add_argument("--corrector-noise", type=float, metavar="STD",
                   help="a shaky hand: std of Gaussian noise on the scripted corrector's actions, in [-1, 1] units; "
                        "the velocities of the states after a correction then echo its actions less, so an actor "
                        f"that imitates them copies its own motion less (DART) (default: {od.corrector_noise})")
    o.add_argument("--mode", choices=("lockstep", "realtime"),
                   help=f"lockstep: paced by the learner, reproducible; realtime: 50 Hz, as a robot (default: {od.mode})")
    o.add_argument("--prior-algo", choices=("auto", "awac"),
                   help="without --prior: train the prior with --algo auto (the best prior from the bag; README, "
                        f"'The best prior') or the chapter's AWAC for --prior-steps (default: {od.prior_algo})")
    o.add_argument("--no-prior", action="store_true", default=None, help="the learner starts from scratch (an ablation)")
    o.add_argument("--no-explore", action="store_true", default=None,
                   help="the policy acts on its mean instead of sampling its Gaussian: the arm goes only where the "
                        "policy or a takeover sends it, and a person's corrections are the exploration (default: "
                        "it samples, with the learner's std)")
    o.add_argument("--action-labels", action="store_true", default=None,
                   help="the scripted corrector also labels every state it leaves to the policy with the action it "
                        "would take (DAgger's labels): the actor imitates the labels, the critic learns from the "
                        "actions the arm took (default: only a takeover's actions are imitated)")
    o.add_argument("--utd", type=int, help=f"gradient steps per environment step (default: {od.utd})")
    o.add_argument("--offline-ratio", type=float, metavar="R",
                   help="share of each batch drawn from the bag, the rest from the session's own steps and a "
                        f"person's takeovers (default: {od.offline_ratio}, RLPD's symmetric sampling)")
    o.add_argument("--imitate-expert", action="store_true", default=None,
                   help="the actor's BC term also on the bag's expert episodes (its demonstrations), as TD3+BC keeps "
                        "an actor near them (default: only on a person's corrections)")
    o.add_argument("--critic-warmup", type=int, metavar="N",
                   help="gradient steps of the critic alone on the bag, with the prior's actor, before the first "
                        f"update (a prior without a critic: --prior-algo auto's) (default: {od.critic_warmup})")
    o.add_argument("--normalize-obs", action="store_true", default=None,
                   help="actor and critic learn on observations z-scored by the bag's statistics (fixed for the "
                        "session; as --prior-algo auto trains the prior), folded into every weights version, so what "
                        "is served takes raw observations (default: raw observations)")
    o.add_argument("--bc-weight", type=float, metavar="W",
                   help="weight of the actor's squared error to a person's actions (and, with --imitate-expert, the "
                        f"bag's expert actions) beside its SAC objective (default: {od.bc_weight})")
    o.add_argument("--lr-decay", action="store_true", default=None,
                   help="the learning rates fall along a cosine to zero over --env-steps, so the session ends on "
                        "settled weights (default: constant rates)")
    o.add_argument("--publish-every", type=int,
                   help=f"environment steps between weights versions (default: {od.publish_every}, 1 s at 50 Hz)")
    o.add_argument("--eval-every", type=int,
                   help=f"environment steps between points of the learning curve (default: {od.eval_every})")
    o.add_argument("--in-process", action="store_true", default=None, help="the same stage in one process, without ROS "
                   "(the reference; ablations)")
    o.add_argument("--from-topics", action="store_true", default=None,
                   help="the learner builds its transitions live from the task's raw topics (joint states, commands, "
                        "goal), as a robot that publishes only standard topics has them, instead of pusher/transition")
    o.add_argument("--actors", type=int, metavar="N",
                   help="N sims, each with its policy node, mux and corrector in namespace /arm1 ... /armN, feed the "
                        "one learner over DDS and act on its weights; --env-steps is the total over them "
                        f"(default: {od.actors})")
    o.add_argument("--success", metavar="CLASSIFIER", help="with --in-process or --from-topics: a success classifier "
                   "(`offline-rl classifier train`) judges each state's success for the learner's reward and the "
                   "episode's end, instead of the simulator (which is still counted beside it, never trained on)")
    o.add_argument("--end-on-success", action="store_true", default=None,
                   help="an episode ends where success is judged (the classifier's or the simulator's); over ROS "
                        "(with --from-topics) the arm's episode too: the policy node labels the classifier's success "
                        "on episode_label, or the sim ends it on its own success; --env-steps need not be whole "
                        "episodes")
    p.set_defaults(func=_run)
