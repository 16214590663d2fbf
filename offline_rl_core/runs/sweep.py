"""A sweep: many training runs from one spec, learners x hyper-parameters x bags x seeds.

The spec is a YAML file (README, 'Sweeps and fleets')::

    name: chapter                  # optional; default: the file's name
    bags: bags/mix.db3             # a bag, a directory of bags, a glob or a list of them; or
                                   # named sets of them ({mix: ..., day1: "fleet/*.db3"}), each swept
    seeds: [0, 1, 2]
    train: {steps: 2000}           # TrainConfig fields every run shares
    grid: {lr: [0.0003, 0.001]}    # every combination of these lists, with each variant:
    variants:                      # each a small grid of its own
      - {algo: bc}
      - {algo: awac, beta: [0.3, 1.0]}
    eval: {episodes: 100, seed: 500000}
    baseline: bc                   # the arm every other one is compared with

An arm is a run's settings less its seed (``awac beta=1``); a run is an arm on one bag set
with one seed, trained as `offline-rl train` trains (``training_run.run_training``) into
DIR/<run>/ beside DIR/<run>/run.json, the run's own spec. Engines run the runs (local worker
processes: ``local_engine``; Ray tasks: ``ray_engine``); this module plans them, keeps the
book and writes DIR/results.jsonl (one row per run), DIR/summary.md and DIR/summary.png.
A run is finished when its metrics.json exists beside a run.json equal to its spec, so
``resume`` skips exactly those; a run that fails is a row with its error and stops no other.
"""

from __future__ import annotations

import itertools
import json
import math
import os
import re
import tempfile
import time
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Callable, Protocol

from ..common.atomic import atomic_path, write_json_atomic, write_text_atomic
from ..common.errors import UserError
from ..common.output_paths import check_output_dir
from ..common.seeds import HELD_OUT, MAX_SEED
from ..data.fleet import check_bags_exist, expand_bags
from ..evaluation.stats import excludes_zero, newcombe_diff_ci, wilson_ci
from ..learners.config import ALGORITHMS, TrainConfig

SPEC_FIELDS = ("name", "bags", "seeds", "train", "grid", "variants", "eval", "baseline")
EVAL_FIELDS = ("episodes", "seed")
CONFIG_FIELDS = {f.name: f for f in fields(TrainConfig)}
DEFAULT_EVAL_EPISODES = 100
RESULTS = "results.jsonl"
RUN_SPEC = "run.json"
_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.-]*")


@dataclass
class SweepRun:
    name: str  # its directory under the sweep's DIR, unique in the sweep
    arm: str  # its settings less the seed, e.g. "awac beta=1"
    bag_set: str
    seed: int
    bags: tuple[str, ...]  # absolute paths of the bags it trains on, in order
    config: dict  # TrainConfig's fields
    eval_episodes: int
    eval_seed: int
    params: dict = field(default_factory=dict)  # the swept settings its arm names

    def record(self) -> dict:
        """What run.json holds: everything the run's result depends on."""
        return {"name": self.name, "arm": self.arm, "bag_set": self.bag_set, "seed": self.seed,
                "bags": list(self.bags), "config": self.config, "params": self.params,
                "eval": {"episodes": self.eval_episodes, "seed": self.eval_seed}}

    def train_config(self) -> TrainConfig:
        return TrainConfig(**self.config)


@dataclass
class SweepSpec:
    name: str
    path: Path
    runs: list[SweepRun]
    baseline: str | None  # an arm
    bag_sets: dict[str, tuple[str, ...]]

    @property
    def arms(self) -> list[str]:
        return list(dict.fromkeys(r.arm for r in self.runs))


# ----------------------------------------------------------------------------- the spec

def load_sweep_spec(path: str | os.PathLike) -> SweepSpec:
    """The sweep a YAML file describes, every run planned and every bag found; UserError,
    one line naming the file and the field, for anything wrong."""
    path = Path(path)
    if not path.is_file():
        raise UserError(f"{path}: no such spec file" if not path.exists() else f"{path}: not a file; expected a YAML spec")
    try:
        from ruamel.yaml import YAML  # a dependency of rosbags

        doc = YAML(typ="safe", pure=True).load(path.read_text())
    except Exception as exc:  # ruamel's parser and scanner errors, bad UTF-8
        raise UserError(f"{path}: not valid YAML ({' '.join(str(exc).split())[:200]})") from exc
    return spec_from_dict(doc, path)


def spec_from_dict(doc, path: Path) -> SweepSpec:
    where = str(path)

    def bad(label: str, expected: str, value) -> UserError:
        return UserError(f"{where}: field {label}: expected {expected}, got {value!r}")

    if not isinstance(doc, dict):
        raise UserError(f"{where}: expected a mapping with the fields {', '.join(SPEC_FIELDS)}")
    for key in doc:
        if key not in SPEC_FIELDS:
            raise UserError(f"{where}: unknown field {key!r}; a sweep spec takes: {', '.join(SPEC_FIELDS)}")
    name = doc.get("name", path.stem)
    if not isinstance(name, str) or not name.strip():
        raise bad("name", "a name", name)
    if "bags" not in doc:
        raise UserError(f"{where}: field bags is missing: name the bags to train on (a bag, a directory of bags, "
                        "a glob, a list of them, or named sets of them)")
    bag_sets = _bag_sets(doc["bags"], path, bad)
    seeds = _seeds(doc.get("seeds", [0]), bad)
    shared = _settings(doc.get("train") or {}, "train", where, lists=False)
    grid = _settings(doc.get("grid") or {}, "grid", where, lists=True)
    variants_doc = doc.get("variants", [{}])
    if not isinstance(variants_doc, list):
        raise bad("variants", "a list of mappings of TrainConfig fields to values or lists", variants_doc)
    if not variants_doc:
        raise UserError(f"{where}: field variants: empty list; nothing to run")
    variants = []
    for i, variant in enumerate(variants_doc):
        settings = _settings(variant or {}, f"variants[{i}]", where, lists=True)
        for key in settings:
            if key in grid:
                raise UserError(f"{where}: field variants[{i}].{key} is in grid too; give it in one of them")
        variants.append(settings)
    eval_doc = doc.get("eval") or {}
    if not isinstance(eval_doc, dict):
        raise bad("eval", "a mapping with episodes and seed", eval_doc)
    for key in eval_doc:
        if key not in EVAL_FIELDS:
            raise UserError(f"{where}: unknown field 'eval.{key}'; eval takes: {', '.join(EVAL_FIELDS)}")
    episodes = eval_doc.get("episodes", DEFAULT_EVAL_EPISODES)
    if isinstance(episodes, bool) or not isinstance(episodes, int) or episodes < 1:
        raise bad("eval.episodes", "a whole number >= 1 (rollouts per run)", episodes)
    eval_seed = eval_doc.get("seed", HELD_OUT)
    if isinstance(eval_seed, bool) or not isinstance(eval_seed, int) or not 0 <= eval_seed <= MAX_SEED - episodes:
        raise bad("eval.seed", f"a whole number from 0 to {MAX_SEED - episodes}", eval_seed)

    runs = plan_runs(shared, grid, variants, bag_sets, seeds, episodes, eval_seed, where)
    spec = SweepSpec(name.strip(), path, runs, None, bag_sets)
    baseline = doc.get("baseline")
    if baseline is not None:
        if not isinstance(baseline, str) or baseline not in spec.arms:
            raise UserError(f"{where}: field baseline: no arm {baseline!r} in the sweep; its arms: {', '.join(spec.arms)}")
        spec.baseline = baseline
    return spec


def _bag_sets(value, path: Path, bad) -> dict[str, tuple[str, ...]]:
    """{set name: its bags (absolute paths)}; relative paths are relative to the spec's folder."""
    named = value if isinstance(value, dict) else {"bags": value}
    if not named:
        raise UserError(f"{path}: field bags: empty; nothing to run")
    out = {}
    for set_name, entries in named.items():
        label = "bags" if not isinstance(value, dict) else f"bags.{set_name}"
        if not isinstance(set_name, str) or not _NAME.fullmatch(set_name):
            raise bad("bags", "bag set names of letters, digits, '_', '.' and '-'", set_name)
        entries = [entries] if isinstance(entries, str) else entries
        if not isinstance(entries, list) or not all(isinstance(e, str) and e for e in entries):
            raise bad(label, "a path or glob, or a list of them", entries)
        if not entries:
            raise UserError(f"{path}: field {label}: empty list; nothing to run")
        where = f"{path}: field {label}:"
        bags = expand_bags([os.path.normpath(path.parent.absolute() / e) for e in entries], what=where)
        check_bags_exist(bags, what=f"{path}: field {label}")
        out[set_name] = tuple(bags)
    return out


def _seeds(value, bad) -> list[int]:
    seeds = [value] if isinstance(value, int) and not isinstance(value, bool) else value
    if not isinstance(seeds, list) or not all(isinstance(s, int) and not isinstance(s, bool) and 0 <= s <= MAX_SEED
                                              for s in seeds):
        raise bad("seeds", f"a list of whole numbers from 0 to {MAX_SEED}", value)
    if not seeds:
        raise bad("seeds", "at least one seed", value)
    if len(set(seeds)) != len(seeds):
        raise bad("seeds", "no seed twice", value)
    return seeds


def _settings(doc, label: str, where: str, lists: bool) -> dict:
    """TrainConfig fields of one section, each value checked (``lists``: each a list of
    values, a single value being a list of one)."""
    if not isinstance(doc, dict):
        raise UserError(f"{where}: field {label}: expected a mapping of TrainConfig fields, got {doc!r}")
    out = {}
    for key, value in doc.items():
        if key not in CONFIG_FIELDS:
            raise UserError(f"{where}: unknown field '{label}.{key}'; TrainConfig's fields: {', '.join(CONFIG_FIELDS)}")
        if lists:
            values = value if isinstance(value, list) else [value]
            if not values:
                raise UserError(f"{where}: field {label}.{key}: empty list; nothing to run")
            checked = [_setting(key, v, f"{label}.{key}", where) for v in values]
            if len(set(map(repr, checked))) != len(checked):
                raise UserError(f"{where}: field {label}.{key}: a value is given twice ({values!r})")
            out[key] = checked
        else:
            if isinstance(value, list):
                raise UserError(f"{where}: field {label}.{key}: expected one value (lists go in grid or variants), "
                                f"got {value!r}")
            out[key] = _setting(key, value, f"{label}.{key}", where)
    return out


def _setting(name: str, value, label: str, where: str):
    """``value`` as TrainConfig's field ``name`` takes it; UserError naming ``label``."""
    default = getattr(TrainConfig, name)
    kind = type(default) if default is not None else (CONFIG_FIELDS[name].metadata.get("kind") or float)
    if name == "algo" and value not in ALGORITHMS:
        raise UserError(f"{where}: field {label}: unknown learner {value!r}; expected one of {', '.join(ALGORITHMS)}")
    if value is None and default is None:
        return None
    ok = (isinstance(value, bool) if kind is bool else
          isinstance(value, int) and not isinstance(value, bool) if kind is int else
          isinstance(value, (int, float)) and not isinstance(value, bool) if kind is float else
          isinstance(value, str))
    if not ok:
        raise UserError(f"{where}: field {label}: expected {kind.__name__}{' or null' if default is None else ''}, "
                        f"got {value!r}")
    value = float(value) if kind is float else value
    try:
        TrainConfig(**{name: value})
    except ValueError as exc:
        text = str(exc)
        flag = "--" + name.replace("_", "-")
        text = text[len(flag):].lstrip(": ") if text.startswith(flag) else text
        raise UserError(f"{where}: field {label}: {text}") from None
    return value


def plan_runs(shared: dict, grid: dict, variants: list[dict], bag_sets: dict[str, tuple[str, ...]],
              seeds: list[int], eval_episodes: int, eval_seed: int, where: str) -> list[SweepRun]:
    """Every run of the sweep, bag set by bag set, arm by arm, seed by seed. An arm names its
    learner and the swept settings it sets that take more than one value in the sweep."""
    combos = []  # (the settings a variant and the grid set, the whole config)
    for variant in variants:
        swept = {**grid, **variant}
        keys = list(swept)
        for values in itertools.product(*(swept[k] for k in keys)):
            chosen = dict(zip(keys, values))
            try:
                config = TrainConfig(**{**shared, **chosen}).to_dict()
            except ValueError as exc:
                raise UserError(f"{where}: the settings {chosen} do not make a run: {exc}") from None
            combos.append((chosen, config))
    varying = {k for k in CONFIG_FIELDS if len({repr(c[k]) for _, c in combos}) > 1}
    arms: dict[str, dict] = {}
    labelled = []
    for chosen, config in combos:
        params = {k: v for k, v in chosen.items() if k in varying and k != "algo"}
        arm = " ".join([config["algo"], *(f"{k}={_fmt(v)}" for k, v in params.items())])
        if arm in arms:
            raise UserError(f"{where}: field variants: the sweep holds the arm {arm!r} twice; give each setting once")
        arms[arm] = config
        labelled.append((arm, params, config))
    runs = []
    for set_name, bags in bag_sets.items():
        for arm, params, config in labelled:
            for seed in seeds:
                stem = re.sub(r"[^A-Za-z0-9_.=+-]", "_", arm.replace(" ", "-"))
                name = f"{stem}{'@' + set_name if len(bag_sets) > 1 else ''}-s{seed}"
                runs.append(SweepRun(name, arm, set_name, seed, bags, config, eval_episodes, eval_seed, params))
    return runs


def _fmt(value) -> str:
    return f"{value:g}" if isinstance(value, float) else str(value)


# ----------------------------------------------------------------------------- one run

def execute_run(run: SweepRun, out_dir: str | os.PathLike, dataset=None) -> dict:
    """Train and evaluate one run into ``out_dir``; its result row, a failure included
    (its error in one line): a run that fails stops no other. ``dataset``: its bags already
    read (``training_run.load_bags``'s result)."""
    from .training_run import run_training

    t0 = time.perf_counter()
    try:
        run_training(list(run.bags), run.train_config(), run.seed, out_dir, run.eval_episodes, run.eval_seed,
                     log=lambda line: None, dataset=dataset, decode_workers=1)
        metrics = json.loads((Path(out_dir) / "metrics.json").read_text())
        return result_row(run, metrics, wall_s=time.perf_counter() - t0)
    except Exception as exc:  # noqa: BLE001 - the run's failure, reported by its name
        return result_row(run, error=one_line(exc), wall_s=time.perf_counter() - t0)


def execute_run_detached(run: SweepRun, dataset=None) -> tuple[dict, dict[str, bytes]]:
    """``execute_run`` into a temporary folder of this machine; the row and the files'
    bytes, for an engine whose runs write nowhere the sweep's DIR is (a cluster's node)."""
    with tempfile.TemporaryDirectory(prefix=f"sweep-{run.name}-") as tmp:
        row = execute_run(run, tmp, dataset)
        files = {p.name: p.read_bytes() for p in sorted(Path(tmp).iterdir()) if p.is_file()}
    return row, files


def store_run_files(run_dir: Path, files: dict[str, bytes]) -> None:
    """A detached run's files into its folder, each atomically, metrics.json last (a run
    is finished once its metrics.json is there)."""
    run_dir.mkdir(parents=True, exist_ok=True)
    for name in sorted(files, key=lambda n: n == "metrics.json"):
        with atomic_path(run_dir / name, suffix=Path(name).suffix or ".tmp") as tmp:
            tmp.write_bytes(files[name])


def one_line(exc: BaseException) -> str:
    text = " ".join(str(exc).split())
    if isinstance(exc, UserError):
        return text
    return f"{type(exc).__name__}: {text}" if text else type(exc).__name__


def result_row(run: SweepRun, metrics: dict | None = None, error: str | None = None,
               wall_s: float | None = None) -> dict:
    """One line of results.jsonl."""
    row = {"name": run.name, "arm": run.arm, "bag_set": run.bag_set, "seed": run.seed,
           "algo": run.config["algo"], "params": run.params, "status": "failed" if metrics is None else "ok",
           "error": error}
    if metrics is not None:
        ev = metrics["eval"]
        row.update({k: ev[k] for k in ("episodes", "successes", "success_rate", "wilson_ci_lo", "wilson_ci_hi",
                                       "mean_final_dist", "mean_return")})
        row.update({"transitions": metrics["transitions"], "dataset_hash": metrics["dataset_hash"],
                    "final_losses": metrics["final_losses"]})
    if wall_s is not None:
        row["wall_s"] = round(wall_s, 3)
    return row


# ----------------------------------------------------------------------------- the book

class Engine(Protocol):
    """Runs runs somewhere; calls ``on_result(run, row)`` in this process as each ends."""

    def describe(self) -> str: ...

    def run(self, runs: list[SweepRun], out: Path, on_result: Callable[[SweepRun, dict], None]) -> None: ...


@dataclass
class SweepOutcome:
    spec: SweepSpec
    rows: list[dict]  # one per run, in the spec's order
    out: Path
    skipped: int  # runs finished before (resume)

    @property
    def failed(self) -> list[dict]:
        return [r for r in self.rows if r["status"] != "ok"]


def finished_runs(spec: SweepSpec, out: Path, resume: bool) -> dict[str, dict]:
    """{run name: its row} of the runs already finished in ``out``. Refuses (UserError) an
    ``out`` that holds a sweep unless ``resume``, and a run folder made with other settings."""
    check_output_dir(out, "--out")
    if not resume and ((out / RESULTS).exists() or any((out / r.name / RUN_SPEC).exists() for r in spec.runs)):
        raise UserError(f"--out {out}: holds a sweep already; --resume continues it, or give another --out")
    done = {}
    for run in spec.runs:
        recorded_path = out / run.name / RUN_SPEC
        if not recorded_path.exists():
            continue
        try:
            recorded = json.loads(recorded_path.read_text())
        except ValueError:
            recorded = None
        if recorded != run.record():
            raise UserError(f"--out {out}: {run.name} there was run with other settings "
                            f"({_first_difference(recorded, run.record())}); give another --out")
        metrics_path = out / run.name / "metrics.json"
        if metrics_path.exists():
            done[run.name] = result_row(run, json.loads(metrics_path.read_text()))
    return done


def _first_difference(old, new, at: str = "") -> str:
    if isinstance(old, dict) and isinstance(new, dict):
        for key in list(new) + [k for k in old if k not in new]:
            if old.get(key) != new.get(key):
                return _first_difference(old.get(key), new.get(key), f"{at}.{key}" if at else key)
    return f"{at or 'run.json'}: {old!r} there, {new!r} in the spec"


class ResultsLog:
    """DIR/results.jsonl: a row appended (and synced) as each run ends, so a killed sweep
    loses no finished run's row; rewritten whole at the end, one row per run."""

    def __init__(self, path: Path, fresh: bool):
        self.path = path
        if fresh or not path.exists():
            write_text_atomic(path, "")

    def append(self, row: dict) -> None:
        fd = os.open(self.path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o666)
        try:
            os.write(fd, (json.dumps(row, sort_keys=True) + "\n").encode())
            os.fsync(fd)
        finally:
            os.close(fd)

    def rewrite(self, rows: list[dict]) -> None:
        write_text_atomic(self.path, "".join(json.dumps(r, sort_keys=True) + "\n" for r in rows))


def run_sweep(spec: SweepSpec, out: str | os.PathLike, engine: Engine, resume: bool = False,
              log: Callable[[str], None] = print) -> SweepOutcome:
    """Run every run of ``spec`` not finished in ``out`` on ``engine``; writes the run
    folders, results.jsonl, summary.md and summary.png."""
    out = Path(out)
    done = finished_runs(spec, out, resume)
    todo = [r for r in spec.runs if r.name not in done]
    out.mkdir(parents=True, exist_ok=True)
    book = ResultsLog(out / RESULTS, fresh=not resume)
    log(f"sweep {spec.name}: {len(spec.runs)} runs ({len(spec.arms)} arms x {len(spec.bag_sets)} bag set(s) x "
        f"{len({r.seed for r in spec.runs})} seed(s))"
        + (f", {len(done)} finished already" if done else "") + (f"; {len(todo)} on {engine.describe()}" if todo else ""))
    for run in todo:
        write_json_atomic(out / run.name / RUN_SPEC, run.record())
    rows = dict(done)

    def on_result(run: SweepRun, row: dict) -> None:
        rows[run.name] = row
        book.append(row)
        if row["status"] == "ok":
            log(f"  {run.name}: success {row['successes']}/{row['episodes']} "
                f"[{row['wilson_ci_lo']:.3f}, {row['wilson_ci_hi']:.3f}]  ({row.get('wall_s', 0):.1f}s)  "
                f"[{len(rows)}/{len(spec.runs)}]")
        else:
            log(f"  {run.name}: FAILED: {row['error']}  [{len(rows)}/{len(spec.runs)}]")

    t0 = time.perf_counter()
    if todo:
        engine.run(todo, out, on_result)
        log(f"  {len(todo)} run(s) took {time.perf_counter() - t0:.1f}s")
    missing = [r for r in todo if r.name not in rows]
    for run in missing:  # an engine that lost a run without a word: a failure, said so
        on_result(run, result_row(run, error="the engine returned no result for this run"))
    ordered = compare_to_baseline(spec, [rows[r.name] for r in spec.runs])
    book.rewrite(ordered)
    outcome = SweepOutcome(spec, ordered, out, len(done))
    write_summary(outcome)
    return outcome


# ----------------------------------------------------------------------------- results

def compare_to_baseline(spec: SweepSpec, rows: list[dict]) -> list[dict]:
    """Each finished row with Newcombe's interval of its success rate minus the baseline
    arm's run on the same bag set and seed (evaluated on the same reset seeds)."""
    if spec.baseline is None:
        return rows
    base = {(r["bag_set"], r["seed"]): r for r in rows if r["arm"] == spec.baseline and r["status"] == "ok"}
    out = []
    for row in rows:
        row = dict(row)
        ref = base.get((row["bag_set"], row["seed"]))
        if row["status"] == "ok" and ref is not None and row["arm"] != spec.baseline:
            lo, hi = newcombe_diff_ci(row["successes"], row["episodes"], ref["successes"], ref["episodes"])
            row.update({"baseline": ref["name"], "diff": round(row["success_rate"] - ref["success_rate"], 6),
                        "diff_ci_lo": round(lo, 6), "diff_ci_hi": round(hi, 6), "significant": excludes_zero(lo, hi)})
        out.append(row)
    return out


def arm_rows(outcome: SweepOutcome) -> list[dict]:
    """One row per (arm, bag set): its finished runs' rollouts pooled over seeds, with
    Wilson's interval, and Newcombe's against the baseline arm pooled the same way."""
    spec = outcome.spec
    groups: dict[tuple[str, str], list[dict]] = {}
    for row in outcome.rows:
        groups.setdefault((row["arm"], row["bag_set"]), []).append(row)
    pooled = {}
    for key, rows in groups.items():
        ok = [r for r in rows if r["status"] == "ok"]
        k, n = sum(r["successes"] for r in ok), sum(r["episodes"] for r in ok)
        dist = sum(r["mean_final_dist"] * r["episodes"] for r in ok) / n if n else math.nan
        pooled[key] = {"arm": key[0], "bag_set": key[1], "runs": len(rows), "failed": len(rows) - len(ok),
                       "successes": k, "episodes": n, "mean_final_dist": dist,
                       "ci": wilson_ci(k, n) if n else (math.nan, math.nan)}
    for (arm, bag_set), row in pooled.items():
        ref = pooled.get((spec.baseline, bag_set)) if spec.baseline else None
        if ref is not None and arm != spec.baseline and row["episodes"] and ref["episodes"]:
            row["diff_ci"] = newcombe_diff_ci(row["successes"], row["episodes"], ref["successes"], ref["episodes"])
            row["diff"] = row["successes"] / row["episodes"] - ref["successes"] / ref["episodes"]
    return list(pooled.values())


def _rate(k: int, n: int, lo: float, hi: float) -> str:
    return f"{k}/{n} = {k / n:.3f} [{lo:.3f}, {hi:.3f}]" if n else "-"


def _table(head: list[str], body: list[list[str]], markdown: bool) -> str:
    if markdown:
        return "\n".join(["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
                         + ["| " + " | ".join(r) + " |" for r in body])
    widths = [max(len(r[i]) for r in [head] + body) for i in range(len(head))]
    fmt = lambda r: "  ".join(c.ljust(w) for c, w in zip(r, widths)).rstrip()  # noqa: E731
    return "\n".join([fmt(head), fmt(["-" * w for w in widths])] + [fmt(r) for r in body])


def format_runs(outcome: SweepOutcome, markdown: bool = False) -> str:
    """Per run: success with Wilson's 95% interval, the final distance, and the difference
    to the baseline's run of the same seed with Newcombe's 95% interval."""
    spec = outcome.spec
    head = ["run", "success [95% Wilson CI]", "final dist (m)"]
    if spec.baseline:
        head += [f"diff vs {spec.baseline} [95% Newcombe CI]", "significant"]
    body = []
    for r in outcome.rows:
        if r["status"] != "ok":
            body.append([r["name"], "FAILED: " + (r["error"] or "")[:80], "-"] + (["-", "-"] if spec.baseline else []))
            continue
        line = [r["name"], _rate(r["successes"], r["episodes"], r["wilson_ci_lo"], r["wilson_ci_hi"]),
                f"{r['mean_final_dist']:.3f}"]
        if spec.baseline:
            line += ([f"{r['diff']:+.3f} [{r['diff_ci_lo']:+.3f}, {r['diff_ci_hi']:+.3f}]",
                      "yes" if r["significant"] else "no"] if "diff" in r else
                     ["(baseline)" if r["arm"] == spec.baseline else "-", "-"])
        body.append(line)
    return _table(head, body, markdown)


def format_arms(outcome: SweepOutcome, markdown: bool = False) -> str:
    """Per arm (and bag set), pooled over its seeds."""
    spec = outcome.spec
    several_sets = len(spec.bag_sets) > 1
    head = ["arm"] + (["bags"] if several_sets else []) + ["runs", "success pooled [95% Wilson CI]", "final dist (m)"]
    if spec.baseline:
        head += [f"diff vs {spec.baseline} [95% Newcombe CI]", "significant"]
    body = []
    for a in arm_rows(outcome):
        line = [a["arm"]] + ([a["bag_set"]] if several_sets else [])
        line += [f"{a['runs'] - a['failed']}/{a['runs']}", _rate(a["successes"], a["episodes"], *a["ci"]),
                 "-" if not a["episodes"] else f"{a['mean_final_dist']:.3f}"]
        if spec.baseline:
            if "diff_ci" in a:
                lo, hi = a["diff_ci"]
                line += [f"{a['diff']:+.3f} [{lo:+.3f}, {hi:+.3f}]", "yes" if excludes_zero(lo, hi) else "no"]
            else:
                line += ["(baseline)" if a["arm"] == spec.baseline else "-", "-"]
        body.append(line)
    return _table(head, body, markdown)


def write_summary(outcome: SweepOutcome) -> None:
    """DIR/summary.md (both tables) and DIR/summary.png (pooled success per arm)."""
    from .plots import plot_arm_success

    spec = outcome.spec
    run0 = spec.runs[0]
    text = (f"# Sweep {spec.name}\n\n{len(spec.runs)} runs; each evaluated on {run0.eval_episodes} held-out rollouts "
            f"(reset seeds {run0.eval_seed}..{run0.eval_seed + run0.eval_episodes - 1}). Success rates with 95% "
            "Wilson intervals" + (f"; differences to {spec.baseline} with Newcombe's hybrid score interval" if
                                  spec.baseline else "") + ".\n\n## Arms (pooled over seeds)\n\n"
            + format_arms(outcome, markdown=True) + "\n\n## Runs\n\n" + format_runs(outcome, markdown=True) + "\n")
    write_text_atomic(outcome.out / "summary.md", text)
    bars = [a for a in arm_rows(outcome) if a["episodes"]]
    if bars:
        several = len(spec.bag_sets) > 1
        plot_arm_success([{"label": a["arm"] + (f"\n@{a['bag_set']}" if several else ""),
                           "rate": a["successes"] / a["episodes"], "ci": a["ci"],
                           "baseline": a["arm"] == spec.baseline} for a in bars],
                         outcome.out / "summary.png", title=f"sweep {spec.name}")
