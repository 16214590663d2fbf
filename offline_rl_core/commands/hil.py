"""`offline-rl hil`: the human-in-the-loop corrections loop over ROS (scripted corrector)."""

from __future__ import annotations

import json

from ..hil import DEFAULT_BAG, EVAL_SEED, HilConfig, run_hil
from ..hil_online import OnlineHilConfig, run_hil_online
from ..seeds import seed_arg


def _run(args) -> int:
    if args.online:
        return _run_online(args)
    cfg = HilConfig(
        out=args.out, rounds=args.rounds, episodes=args.episodes, prior=args.prior, bags=args.bag or [DEFAULT_BAG],
        seed=args.seed, prior_steps=args.prior_steps, steps=args.steps, correction_ratio=args.correction_ratio,
        eval_episodes=args.eval_episodes, eval_seed=args.eval_seed, patience=args.patience,
        hold_steps=args.hold_steps, grace_steps=args.grace_steps, beta=args.beta, noise=args.noise, reaction_delay=args.reaction_delay,
    )
    summary = run_hil(cfg)
    print(json.dumps({k: summary[k] for k in ("prior_success", "final_success", "diff_ci_lo", "diff_ci_hi",
                                              "intervention_rate_first", "intervention_rate_last", "wall_seconds")}))
    return 0


def _run_online(args) -> int:
    cfg = OnlineHilConfig(
        out=args.out if args.out != HilConfig().out else OnlineHilConfig().out, env_steps=args.env_steps,
        seed=args.seed, prior=args.prior, no_prior=args.no_prior, prior_steps=args.prior_steps,
        prior_algo=args.prior_algo,
        bags=args.bag or [DEFAULT_BAG], corrector=args.corrector, mode=args.mode, utd=args.utd,
        publish_every=args.publish_every, eval_every=args.eval_every, eval_episodes=args.eval_episodes,
        eval_seed=args.eval_seed, in_process=args.in_process)
    summary = run_hil_online(cfg)
    print(json.dumps({k: summary[k] for k in ("prior_success", "final_success", "final_ci", "to", "intervention_rate",
                                              "wall_seconds")}))
    return 0


def register(subparsers) -> None:
    d = HilConfig()
    p = subparsers.add_parser(
        "hil",
        help="HIL-SERL corrections loop over ROS: serve, correct, record, retrain, reload",
        description="Runs ROUNDS rounds: serve the prior (policy node, hot reload), run EPISODES lockstep episodes with "
        "the scripted corrector taking over through the mux, record them (recorder --passive), retrain AWAC from the "
        "served checkpoint on the offline bag plus all corrections (trainer node, --correction-ratio), reload. "
        "Writes DIR/summary.json and DIR/rounds.png. With --online: the HIL-SERL stage itself, the online "
        "learner fine-tuning the prior from the live stream while the policy node acts (DIR/summary.json with the "
        "learning curve, DIR/online.png).",
    )
    p.add_argument("--out", default=d.out, metavar="DIR", help="output directory (default: %(default)s)")
    p.add_argument("--rounds", type=int, default=d.rounds, help="correction rounds (default: %(default)s)")
    p.add_argument("--episodes", type=int, default=d.episodes, help="corrected episodes per round (default: %(default)s)")
    p.add_argument("--prior", metavar="CKPT", help="checkpoint to start from (default: train AWAC on --bag (--online: see --prior-algo), or reuse "
                   "runs/demo/awac/policy.pt when it was trained so)")
    p.add_argument("--bag", action="append", metavar="PATH", help=f"offline bag(s) of the prior (default: {DEFAULT_BAG})")
    p.add_argument("--seed", type=seed_arg, default=d.seed, help="seed of training and of the corrector (default: %(default)s)")
    p.add_argument("--prior-steps", type=int, default=d.prior_steps, help="steps of the prior's training (default: %(default)s)")
    p.add_argument("--steps", type=int, default=d.steps, help="retraining steps per round (default: %(default)s)")
    p.add_argument("--correction-ratio", type=float, default=d.correction_ratio,
                   help="share of each batch from correction runs (default: %(default)s)")
    p.add_argument("--beta", type=float, default=d.beta, help="AWAC temperature of the retraining (default: %(default)s)")
    p.add_argument("--eval-episodes", type=int, default=d.eval_episodes,
                   help="held-out rollouts per evaluation (default: %(default)s)")
    p.add_argument("--eval-seed", type=seed_arg, default=EVAL_SEED, help="first held-out reset seed (default: %(default)s)")
    c = p.add_argument_group("scripted corrector")
    c.add_argument("--patience", type=int, default=d.patience, help="k: steps without progress before a takeover (default: %(default)s)")
    c.add_argument("--hold-steps", type=int, default=d.hold_steps, help="m: steps before handing back (default: %(default)s)")
    c.add_argument("--grace-steps", type=int, default=d.grace_steps,
                   help="states at an episode's start before progress is judged (default: %(default)s)")
    c.add_argument("--noise", type=float, default=d.noise, help="std of noise on the corrections (default: %(default)s)")
    c.add_argument("--reaction-delay", type=int, default=d.reaction_delay, help="steps of reaction delay (default: %(default)s)")
    o = p.add_argument_group("online stage (--online)")
    od = OnlineHilConfig()
    o.add_argument("--online", action="store_true", help="run the online learner instead of offline rounds "
                   "(default output directory: runs/hil-online)")
    o.add_argument("--env-steps", type=int, default=od.env_steps, help="environment steps of the session "
                   "(default: %(default)s, 400 s of robot time at 50 Hz)")
    o.add_argument("--corrector", choices=("scripted", "keyboard", "none"), default=od.corrector,
                   help="who takes over: the scripted stand-in, a person at this terminal (realtime), or nobody "
                        "(default: %(default)s)")
    o.add_argument("--mode", choices=("lockstep", "realtime"), default=od.mode,
                   help="lockstep: paced by the learner, reproducible; realtime: 50 Hz, as a robot (default: %(default)s)")
    o.add_argument("--prior-algo", choices=("auto", "awac"), default=od.prior_algo,
                   help="without --prior: train the prior with --algo auto (the best prior from the bag; README, "
                        "'The best prior') or the chapter's AWAC for --prior-steps (default: %(default)s)")
    o.add_argument("--no-prior", action="store_true", help="the learner starts from scratch (an ablation)")
    o.add_argument("--utd", type=int, default=od.utd, help="gradient steps per environment step (default: %(default)s)")
    o.add_argument("--publish-every", type=int, default=od.publish_every,
                   help="environment steps between weights versions (default: %(default)s, 1 s at 50 Hz)")
    o.add_argument("--eval-every", type=int, default=od.eval_every,
                   help="environment steps between points of the learning curve (default: %(default)s)")
    o.add_argument("--in-process", action="store_true", help="the same stage in one process, without ROS "
                   "(the reference; ablations)")
    p.set_defaults(func=_run)
