"""Datasets both ways: Minari (Farama's offline-RL dataset format) and d3rlpy's MDPDataset.

Minari stores an episode as one sequence of observations (T + 1 of them: each step's
observation and the last one's next), T actions, rewards, terminations and truncations,
and per-step ``infos``. A bag's transitions map onto that one episode per run of rows with
the same episode id; where a row's ``next_obs`` is not the next row's ``obs`` (a step lost
in recording) a new Minari episode starts, so no row is changed to fit. What Minari has no
field for (who acted, the episode id and step, success) goes in ``infos`` at index t + 1
for step t (index 0 is the start, where Minari's own DataCollector puts the reset's info),
so ``from_minari(to_minari(bag))`` gives the bag's rows back. The spaces are the task's:
``Box(-inf, inf, (obs_dim,))`` observations and ``Box(-1, 1, (act_dim,))`` actions, float32,
sized from the data (any task's); a pusher-reach dataset names its Gymnasium env, so
``dataset.recover_environment()`` makes the env it was recorded on. Reading one back, the
task is given (default pusher_reach) and its sizes must be the dataset's.

Minari keeps datasets under ``MINARI_DATASETS_PATH`` (default ``~/.minari/datasets``); a
dataset is written under a hidden staging directory there and moved into place whole.

``d3rlpy_dataset`` gives d3rlpy's ``MDPDataset``. d3rlpy reads each step's next observation
from the next row, as Minari does, but keeps none for an episode's last step: the last
step of an episode that did not terminate is not a transition it trains on. Episodes end at
termination, truncation, a change of episode id or of the observation chain, and the end
of the data.
"""

from __future__ import annotations

import contextlib
import os
import shutil
from pathlib import Path

import numpy as np

from ..common.errors import UserError
from ..task.spec import DEFAULT_TASK, TaskSpec, load_task
from .transitions import SOURCE_NAMES, Transitions

MINARI_INSTALL = "pip install 'offline_rl_core[interop]' (or: pip install 'minari[hdf5]')"
INFO_FIELDS = ("episode", "step", "source", "success")  # the bag's fields Minari has no place for


def import_minari():
    try:
        import minari
    except ImportError:
        raise UserError(f"minari is not installed; {MINARI_INSTALL}") from None
    return minari


def episode_runs(data: Transitions) -> list[slice]:
    """Row ranges that are one Minari episode each: consecutive rows of one episode id whose
    observations chain (each row's ``next_obs`` is the next row's ``obs``)."""
    n = len(data)
    if n == 0:
        return []
    same_episode = data.episode[1:] == data.episode[:-1]
    chained = np.all(data.next_obs[:-1] == data.obs[1:], axis=1)
    starts = np.concatenate([[0], np.flatnonzero(~(same_episode & chained)) + 1])
    stops = np.concatenate([starts[1:], [n]])
    return [slice(int(a), int(b)) for a, b in zip(starts, stops)]


def spaces(obs_dim: int, act_dim: int):
    """The task's observation and action spaces at these sizes."""
    from gymnasium import spaces as gym_spaces

    return (gym_spaces.Box(-np.inf, np.inf, shape=(obs_dim,), dtype=np.float32),
            gym_spaces.Box(-1.0, 1.0, shape=(act_dim,), dtype=np.float32))


def minari_buffers(data: Transitions) -> list:
    """One ``minari.data_collector.EpisodeBuffer`` per run of ``episode_runs``."""
    from minari.data_collector import EpisodeBuffer

    buffers = []
    for i, rows in enumerate(episode_runs(data)):
        first = rows.start
        infos = {name: np.concatenate([getattr(data, name)[first:first + 1], getattr(data, name)[rows]])
                 for name in INFO_FIELDS}
        infos["success"][0] = False  # the start: nothing reached yet
        infos["step"][0] = max(int(data.step[first]) - 1, 0)
        buffers.append(EpisodeBuffer(
            id=i,
            observations=np.concatenate([data.obs[rows], data.next_obs[rows.stop - 1:rows.stop]]).astype(np.float32),
            actions=data.action[rows].astype(np.float32),
            rewards=data.reward[rows].astype(np.float32),
            terminations=data.terminated[rows].astype(bool),
            truncations=data.truncated[rows].astype(bool),
            infos=infos,
        ))
    return buffers


def minari_root() -> Path:
    return Path(os.environ.get("MINARI_DATASETS_PATH") or Path.home() / ".minari" / "datasets")


def to_minari(data: Transitions, dataset_id: str, description: str | None = None, task: TaskSpec | None = None,
              **metadata) -> Path:
    """Write ``data`` (of ``task``, default pusher_reach) as the Minari dataset ``dataset_id``;
    returns its directory. Refuses an ID that exists; a dataset appears whole or not at all.
    ``metadata``: Minari's own (``author``, ``author_email``, ``code_permalink``)."""
    minari = import_minari()
    from minari.dataset.minari_dataset import parse_dataset_id
    from minari.namespace import create_namespace, list_local_namespaces
    from minari.storage import get_dataset_path

    if len(data) == 0:
        raise UserError(f"{dataset_id}: no transitions to export")
    try:
        namespace = parse_dataset_id(dataset_id)[0]
    except (ValueError, AssertionError):
        raise UserError(f"{dataset_id}: not a Minari dataset ID; expected [NAMESPACE/]NAME-vN, e.g. pusher/mix-v0") \
            from None
    target = Path(get_dataset_path(dataset_id))
    if target.exists():
        raise UserError(f"{dataset_id}: a Minari dataset of that ID exists in {minari_root()}; export under another "
                        f"name or version, or delete it first (minari delete {dataset_id})")
    obs_space, act_space = spaces(data.obs.shape[1], data.action.shape[1])
    env = None
    if (task or load_task()).digest == load_task(DEFAULT_TASK).digest:  # the one task with a Gymnasium env
        from ..task.gym_env import ENV_ID  # registers the env

        env = ENV_ID
    root = minari_root()
    staging = root / f".staging-{os.getpid()}"
    try:
        with _datasets_path(staging):
            minari.create_dataset_from_buffers(
                dataset_id, minari_buffers(data), env=env, eval_env=env, observation_space=obs_space,
                action_space=act_space, description=description, algorithm_name="pusher-rl bag export", **metadata)
        if namespace is not None and namespace not in list_local_namespaces():
            create_namespace(namespace)
        target.parent.mkdir(parents=True, exist_ok=True)
        os.rename(staging / dataset_id, target)  # the whole dataset at once
    except OSError as exc:
        raise UserError(f"{dataset_id}: cannot write the dataset under {root}: {exc}") from None
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    return target


@contextlib.contextmanager
def _datasets_path(path: Path):
    """Minari reads its root from the environment at each call: point it at ``path`` meanwhile."""
    before = os.environ.get("MINARI_DATASETS_PATH")
    os.environ["MINARI_DATASETS_PATH"] = str(path)
    try:
        yield
    finally:
        if before is None:
            os.environ.pop("MINARI_DATASETS_PATH", None)
        else:
            os.environ["MINARI_DATASETS_PATH"] = before


def from_minari(dataset_id: str, source: int | None = None, task: TaskSpec | None = None) -> Transitions:
    """The transitions of the Minari dataset ``dataset_id``, which must have ``task``'s sizes
    (default pusher_reach). Who acted, episode ids, steps and success come from the episodes'
    infos where the dataset has them (pusher-rl's exports do); else ``source`` (required
    then), Minari's episode ids, 0.. and False."""
    task = task or load_task()
    minari = import_minari()
    from gymnasium import spaces as gym_spaces

    try:
        dataset = minari.load_dataset(dataset_id)
    except FileNotFoundError:
        raise UserError(f"{dataset_id}: no such Minari dataset in {minari_root()}") from None
    except (ValueError, KeyError, OSError) as exc:
        raise UserError(f"{dataset_id}: cannot open the Minari dataset ({str(exc).splitlines()[0][:160]})") from None
    for role, space in (("observation", dataset.observation_space), ("action", dataset.action_space)):
        if not isinstance(space, gym_spaces.Box) or len(space.shape) != 1:
            raise UserError(f"{dataset_id}: its {role} space is {space}; pusher-rl takes flat Box observations "
                            f"and actions")
    obs_dim, act_dim = dataset.observation_space.shape[0], dataset.action_space.shape[0]
    if (obs_dim, act_dim) != (task.obs_dim, task.act_dim):
        raise UserError(f"{dataset_id}: observations of {obs_dim} and actions of {act_dim} values; task {task.name} "
                        f"has {task.obs_dim} and {task.act_dim} (give the dataset's task with --task)")
    parts = [_episode_transitions(dataset_id, ep, source) for ep in dataset.iterate_episodes()]
    if not parts:
        raise UserError(f"{dataset_id}: the dataset has no episodes")
    data = Transitions.concatenate(parts)
    outside = np.abs(data.action) > 1.0
    if outside.any():
        raise UserError(f"{dataset_id}: {int(outside.any(axis=1).sum())} actions lie outside [-1, 1] "
                        f"(largest {float(np.abs(data.action).max()):g}); pusher-rl's actions are normalised to "
                        f"[-1, 1]: rescale them first")
    return data


def _episode_transitions(dataset_id: str, ep, source: int | None) -> Transitions:
    n = len(ep.rewards)
    obs = np.asarray(ep.observations, dtype=np.float32)
    if obs.shape[0] != n + 1:
        raise UserError(f"{dataset_id}: episode {ep.id} has {obs.shape[0]} observations for {n} steps "
                        f"(Minari stores steps + 1)")
    infos = ep.infos or {}

    def info(name: str, default: np.ndarray) -> np.ndarray:
        values = infos.get(name)
        return np.asarray(values)[1:] if values is not None and len(values) == n + 1 else default

    if "source" not in infos and source is None:
        raise UserError(f"{dataset_id}: the dataset does not record who acted; say it with --source "
                        f"({', '.join(SOURCE_NAMES.values())})")
    return Transitions(
        obs=obs[:-1], action=np.asarray(ep.actions, dtype=np.float32).reshape(n, -1),
        reward=np.asarray(ep.rewards, dtype=np.float32).reshape(n), next_obs=obs[1:],
        terminated=np.asarray(ep.terminations, dtype=bool).reshape(n),
        truncated=np.asarray(ep.truncations, dtype=bool).reshape(n),
        success=info("success", np.zeros(n, dtype=bool)).astype(bool),
        episode=info("episode", np.full(n, ep.id)).astype(np.int64),
        step=info("step", np.arange(n)).astype(np.int64),
        source=info("source", np.full(n, source if source is not None else 0)).astype(np.int64),
    )


# ------------------------------------------------------------------ d3rlpy
def import_d3rlpy():
    """d3rlpy, imported without its banner noise: gym's deprecation notice on stderr and
    structlog info lines for every dataset it builds."""
    import io
    import logging

    try:
        with contextlib.redirect_stderr(io.StringIO()):
            import d3rlpy
    except ImportError:
        raise UserError("d3rlpy is not installed; pip install 'offline_rl_core[bench]' (or: pip install "
                        "d3rlpy==2.8.1)") from None
    with contextlib.suppress(Exception):
        import structlog

        structlog.configure(wrapper_class=structlog.make_filtering_bound_logger(logging.WARNING))
    return d3rlpy


def d3rlpy_dataset(data: Transitions):
    """The transitions as a d3rlpy ``MDPDataset`` with a continuous action space. An episode
    ends at termination (no bootstrapping) or as a timeout: truncation, a change of episode
    id or of the observation chain (``episode_runs``), or the end of the data."""
    d3rlpy = import_d3rlpy()

    ends = np.zeros(len(data), dtype=bool)
    ends[[rows.stop - 1 for rows in episode_runs(data)]] = True
    return d3rlpy.dataset.MDPDataset(
        observations=data.obs.astype(np.float32),
        actions=data.action.astype(np.float32),
        rewards=data.reward.astype(np.float32).reshape(-1, 1),
        terminals=data.terminated.astype(np.float32),
        timeouts=((data.truncated | ends) & ~data.terminated).astype(np.float32),
        action_space=d3rlpy.ActionSpace.CONTINUOUS,
    )
