"""`hipode collect`: build D4RL-style MuJoCo datasets here, as Minari datasets.

One training run per (env, seed), PPO or SAC as the recipe says, trains the behaviour
policies; its checkpoints, the medium-replay transitions and rollout chunks live under
`<dataset root>/collect/<env>-seed<seed>/`, so each policy is trained once and reused by every
kind, and an interrupted collection resumes from the last checkpoint and chunk. The recipe is
stages/collect.toml.
"""

from __future__ import annotations

import contextlib
import json
import os
import time
import tomllib
from collections.abc import Iterator
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from hipode_pipeline.console import progress, rate_text
from hipode_pipeline.data.bands import (
    ALLOW_FLAG,
    POLICIES_OF_KIND,
    OffBandError,
    band_record,
    dataset_band,
    off_band_text,
)
from hipode_pipeline.data.env_batch import make_env
from hipode_pipeline.data.minari_write import (
    dataset_dir,
    episode_spans,
    split_episodes,
    write_minari_dataset,
)
from hipode_pipeline.data.policies import BehaviourPolicy, load_policy, save_policy
from hipode_pipeline.data.ppo import (
    ActionFn,
    PPOConfig,
    PPOTrainer,
    RolloutBlock,
    load_checkpoint,
    run_policy,
)
from hipode_pipeline.data.sac import SACConfig, SACTrainer
from hipode_pipeline.errors import (
    CollectionBusyError,
    CollectionInterrupted,
    DataFormatError,
    NotCollectableError,
)
from hipode_pipeline.evaluate import evaluate_policy
from hipode_pipeline.files import save_npz_atomic, save_torch_atomic, write_json_atomic
from hipode_pipeline.paths import stages_dir, use_datasets_root
from hipode_pipeline.tasks import Task
from hipode_pipeline.threads import torch_threads
from hipode_pipeline.versions import package_versions

RECIPE_FILE = "collect.toml"
# the behaviour policies each dataset kind needs
POLICIES_BY_KIND = POLICIES_OF_KIND
# fixed ids that separate the seed streams of rollouts and evaluations per policy
STREAM_IDS = {"random": 1, "medium": 2, "expert": 3}
# tests set this to stop training right after the first checkpoint at or past this many steps
STOP_AFTER_STEPS: int | None = None
TRAINERS = {"ppo": PPOTrainer, "sac": SACTrainer}
# a medium-replay history longer than this many times D4RL's size is subsampled to it
SUBSAMPLE_ABOVE = 1.5


@dataclass(frozen=True)
class CollectRecipe:
    """How one env family's datasets are built (a section of stages/collect.toml)."""

    env: str  # env family, e.g. hopper
    profile: str  # "full" (the real recipe) or "quick" (tests)
    trainer: str  # behaviour-policy trainer: "ppo" or "sac"
    ppo: PPOConfig  # PPO's settings (used when trainer is "ppo")
    sac: SACConfig  # SAC's settings (used when trainer is "sac")
    medium_check_from: float  # normalized recent training return from which policies are evaluated
    medium_range: tuple[float, float]  # evaluated normalized return that makes the medium policy
    # where D4RL's medium policy scores: a medium policy outside it makes the data off-band
    medium_band: tuple[float, float] | None
    expert_band: tuple[float, float] | None  # the same for the expert policy
    medium_check_every: int  # env steps between two evaluated medium candidates (0: each iteration)
    medium_max_steps: int  # env steps after which the current policy is medium regardless
    expert_target: float  # evaluated normalized return that ends expert training early
    expert_steps: int  # env-step budget of expert training
    recent_episodes: int  # training episodes averaged for the targets
    checkpoint_every: int  # env steps between training checkpoints
    eval_episodes: int  # episodes of each behaviour policy's measured return
    rollout_envs: int  # envs stepped side by side in rollouts
    rollout_chunk: int  # transitions per rollout chunk file
    stochastic_rollouts: bool  # sample from the Gaussian policy (else its mean)
    medium_replay_size: int  # D4RL's medium-replay size: longer histories are subsampled (0: no)
    random_size: int  # transitions of a random dataset
    medium_size: int  # transitions of a medium dataset (and of medium-expert's medium half)
    expert_size: int  # transitions of an expert dataset (and of medium-expert's expert half)

    def to_dict(self) -> dict[str, Any]:
        return {**asdict(self), "ppo": self.ppo.to_dict(), "sac": self.sac.to_dict()}

    def trainer_config(self) -> PPOConfig | SACConfig:
        return self.ppo if self.trainer == "ppo" else self.sac

    def bands(self) -> dict[str, tuple[float, float] | None]:
        return {"medium": self.medium_band, "expert": self.expert_band}

    def rollout_size(self, stream: str) -> int:
        """Transitions of one rollout stream: random, medium or expert."""
        return {"random": self.random_size, "medium": self.medium_size, "expert": self.expert_size}[
            stream
        ]


def load_recipe(env: str, profile: str = "full", path: Path | None = None) -> CollectRecipe:
    """The recipe of `env` under `profile`: [defaults] < [env] < [profiles.<profile>]."""
    path = path or stages_dir() / RECIPE_FILE
    with open(path, "rb") as f:
        data = tomllib.load(f)
    profiles = data.get("profiles", {})
    if profile not in profiles:
        raise DataFormatError(path, "profiles", f"one of {sorted(profiles)}", repr(profile))
    if env not in data:
        raise DataFormatError(path, env, f"a [{env}] recipe section")
    values: dict[str, Any] = {}
    ppo: dict[str, Any] = {}
    sac: dict[str, Any] = {}
    for layer in (data["defaults"], data[env], profiles[profile]):
        layer = dict(layer)
        ppo.update(layer.pop("ppo", {}))
        sac.update(layer.pop("sac", {}))
        values.update(layer)
    names = {f for f in CollectRecipe.__dataclass_fields__} - {"env", "profile", "ppo", "sac"}
    unknown, missing = sorted(set(values) - names), sorted(names - set(values))
    if unknown:
        raise DataFormatError(path, unknown[0], f"one of {sorted(names)}", "an unknown key")
    if missing:
        raise DataFormatError(path, missing[0], "a value in [defaults]", "nothing")
    values["medium_range"] = tuple(float(v) for v in values["medium_range"])
    for key in ("medium_band", "expert_band"):
        band = values[key]
        if not isinstance(band, list) or len(band) not in (0, 2):
            raise DataFormatError(path, f"{env}.{key}", "[low, high] or [] (no band)", band)
        values[key] = tuple(float(v) for v in band) if band else None
    if values["trainer"] not in TRAINERS:
        raise DataFormatError(
            path, f"{env}.trainer", f"one of {sorted(TRAINERS)}", values["trainer"]
        )
    return CollectRecipe(
        env=env,
        profile=profile,
        ppo=PPOConfig.from_dict(ppo, str(path)),
        sac=SACConfig.from_dict(sac, str(path)),
        **values,
    )


@dataclass
class CollectResult:
    """What one `collect` call built (or found already built)."""

    dataset_ids: list[str]  # Minari ids of the dataset(s) asked for
    seconds: float  # wall time of this call
    policy_returns: dict[str, float]  # behaviour policy -> mean measured return
    normalized_scores: dict[str, float] = field(default_factory=dict)  # same, D4RL-normalized
    transitions: int = 0  # transitions in the dataset
    episodes: int = 0  # episodes in the dataset
    reused: bool = False  # the dataset existed and was left as it was
    phase_seconds: dict[str, float] = field(default_factory=dict)  # train/evaluate/rollout/write
    steps_per_second: dict[str, float] = field(default_factory=dict)  # env steps/s per phase
    path: str = ""  # dataset folder
    band: dict[str, Any] | None = None  # behaviour policies against their bands (data.bands)

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


# ---- work folder -----------------------------------------------------------------------------


def work_dir(root: Path, env: str, seed: int) -> Path:
    return root / "collect" / f"{env}-seed{seed}"


def _load_block(path: Path) -> RolloutBlock:
    try:
        with np.load(path, allow_pickle=False) as data:
            return RolloutBlock(**{k: data[k] for k in RolloutBlock.__dataclass_fields__})
    except Exception as error:
        raise DataFormatError(
            path, "chunk", "an .npz rollout chunk written by hipode collect", error
        ) from None


def _concat_blocks(blocks: list[RolloutBlock], axis: int) -> RolloutBlock:
    return RolloutBlock(
        **{
            k: np.concatenate([getattr(b, k) for b in blocks], axis=axis)
            for k in RolloutBlock.__dataclass_fields__
        }
    )


def _stream_seed(seed: int, stream: str, index: int) -> int:
    """Independent, reproducible seeds for each (seed, stream, chunk) triple."""
    return int(np.random.SeedSequence([seed, STREAM_IDS[stream], index]).generate_state(1)[0])


@contextlib.contextmanager
def work_lock(work: Path) -> Iterator[None]:
    """Hold `work/.lock` (our pid) so two collections never write the same work folder."""
    lock = work / ".lock"
    for _ in range(2):
        try:
            fd = os.open(lock, os.O_CREAT | os.O_EXCL | os.O_WRONLY)
            break
        except FileExistsError:
            text = lock.read_text().strip()
            owner = int(text) if text.isdigit() else 0
            if owner and _process_alive(owner):
                raise CollectionBusyError(
                    f"{work}: another collection (pid {owner}) is using this work folder; "
                    "wait for it to finish or stop it"
                ) from None
            lock.unlink(missing_ok=True)  # left by a process that was killed
    else:
        raise CollectionBusyError(f"{lock}: could not take the lock")
    with os.fdopen(fd, "w") as f:
        f.write(str(os.getpid()))
    try:
        yield
    finally:
        lock.unlink(missing_ok=True)


def _process_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


# ---- training --------------------------------------------------------------------------------


def train_behaviour_policies(
    task: Task,
    recipe: CollectRecipe,
    work: Path,
    seed: int,
    need_expert: bool,
    show_progress: bool = True,
) -> tuple[dict[str, Any], int]:
    """Run (or resume) the trainer until the medium and, if asked, the expert policy exist.

    Returns the milestones ({"medium": info, "expert": info, ...}) and the env steps trained
    in this call; the policies are
    work/policy-<name>.pt and the medium-replay transitions work/replay/<start step>.npz.
    A policy that missed its target by the budget it was trained to is trained on when the
    recipe's budget has grown since (the checkpoint is where it stopped).
    """
    checkpoint = checkpoint_path(work, recipe)
    milestones: dict[str, Any] = {}
    seconds = 0.0
    if checkpoint.exists():
        state = load_checkpoint(checkpoint)
        milestones, seconds = json.loads(state["milestones"]), float(state["wall_seconds"])
        _check_same_recipe(state, recipe, checkpoint)
        milestones = _reopen_under_larger_budget(milestones, recipe, int(state["steps"]), work)
    if "medium" in milestones and (not need_expert or "expert" in milestones):
        return milestones, 0
    trainer = TRAINERS[recipe.trainer](
        task.env_id, recipe.trainer_config(), seed, recipe.recent_episodes
    )
    if checkpoint.exists():
        trainer.load_state_dict(state, checkpoint)
    replay_dir = work / "replay"
    replay_dir.mkdir(parents=True, exist_ok=True)
    for stale in replay_dir.glob("*.npz"):
        # a chunk written after the last checkpoint is replayed again: drop the old copy
        if int(stale.stem) >= trainer.steps:
            stale.unlink()
    pending: list[RolloutBlock] = []
    pending_start, last_checkpoint = trainer.steps, trainer.steps
    last_medium_check = -recipe.medium_check_every  # the first candidate is checked at once
    total = recipe.expert_steps if need_expert else recipe.medium_max_steps
    started, start_steps = time.perf_counter(), trainer.steps

    def save_checkpoint() -> None:
        nonlocal pending, pending_start, last_checkpoint
        if pending:
            save_npz_atomic(
                replay_dir / f"{pending_start:012d}.npz", _concat_blocks(pending, 0).arrays()
            )
        pending, pending_start, last_checkpoint = [], trainer.steps, trainer.steps
        state = trainer.state_dict()
        state["milestones"] = json.dumps(milestones)
        state["targets"] = json.dumps(_targets(recipe))
        state["wall_seconds"] = seconds + time.perf_counter() - started
        save_torch_atomic(checkpoint, state)

    def policy_info(name: str, normalized: float, reached: bool) -> dict[str, Any]:
        return {
            "file": f"policy-{name}.pt",
            "train_steps": trainer.steps,
            "train_iterations": trainer.iteration,
            "train_episodes": trainer.episodes_done,
            "train_seconds": round(seconds + time.perf_counter() - started, 3),
            "train_return": trainer.recent_return(),
            "train_normalized": normalized,
            "target_reached": reached,
        }

    with progress(disable=not show_progress) as prog:
        bar = prog.add_task(
            f"{recipe.trainer.upper()} {task.env}",
            total=total,
            completed=trainer.steps,
            rate="",
            info="",
        )
        while not ("medium" in milestones and (not need_expert or "expert" in milestones)):
            block, _ = trainer.train_iteration()
            ret = trainer.recent_return()
            normalized = task.normalized_score(ret) if np.isfinite(ret) else float("nan")
            enough = len(trainer.recent_returns) >= recipe.recent_episodes
            changed = False
            if "medium" not in milestones:
                pending.append(block)
                check: dict[str, Any] = {}
                due = trainer.steps - last_medium_check >= recipe.medium_check_every
                if enough and due and normalized >= recipe.medium_check_from:
                    last_medium_check = trainer.steps
                    check = policy_check(
                        task, recipe, trainer.policy(), seed, "medium", trainer.iteration
                    )
                low, high = recipe.medium_range
                reached = bool(check) and low <= check["normalized"] <= high
                if reached or trainer.steps >= recipe.medium_max_steps:
                    info = {**policy_info("medium", normalized, reached), "check": check}
                    save_policy(trainer.policy(), work / "policy-medium.pt", info)
                    milestones["medium"] = info
                    changed = True
            elif need_expert:
                # expert: the best evaluated snapshot, checked once per checkpoint interval
                final = trainer.steps >= recipe.expert_steps
                if final or trainer.steps - last_checkpoint >= recipe.checkpoint_every:
                    check = policy_check(
                        task, recipe, trainer.policy(), seed, "expert", trainer.iteration
                    )
                    # the learning curve of the expert search, kept in the dataset's metadata
                    milestones.setdefault("expert_checks", []).append(
                        {"steps": trainer.steps, "normalized": round(check["normalized"], 2)}
                    )
                    best = milestones.get("expert_candidate", {}).get("check", {})
                    if check["normalized"] > best.get("normalized", -np.inf):
                        info = {**policy_info("expert", normalized, False), "check": check}
                        save_policy(trainer.policy(), work / "policy-expert.pt", info)
                        milestones["expert_candidate"] = info
                    reached = check["normalized"] >= recipe.expert_target
                    if reached or final:
                        milestones["expert"] = {
                            **milestones["expert_candidate"],
                            "target_reached": reached,
                        }
                        changed = True
            if changed or trainer.steps - last_checkpoint >= recipe.checkpoint_every:
                save_checkpoint()
                if STOP_AFTER_STEPS is not None and trainer.steps >= STOP_AFTER_STEPS:
                    raise CollectionInterrupted(
                        f"stopped after the checkpoint at {trainer.steps} steps"
                    )
            elapsed = time.perf_counter() - started
            goal = "medium from" if "medium" not in milestones else "expert at"
            target = (
                recipe.medium_check_from if "medium" not in milestones else recipe.expert_target
            )
            prog.update(
                bar,
                completed=min(trainer.steps, total),
                rate=rate_text(trainer.steps - start_steps, elapsed),
                info=f"return {ret:,.0f} ({normalized:.1f} normalized, {goal} {target:g})",
            )
    return milestones, trainer.steps - start_steps


def checkpoint_path(work: Path, recipe: CollectRecipe) -> Path:
    return work / f"{recipe.trainer}.pt"


def reopened_milestones(milestones: dict[str, Any], recipe: CollectRecipe, steps: int) -> list[str]:
    """The policies that missed their target only because the budget ran out, which has grown
    since: their search goes on from the checkpoint (`steps`). A medium search can go on only
    if no expert training followed it (its replay history must stay contiguous)."""
    medium, expert = milestones.get("medium"), milestones.get("expert")
    if (
        medium
        and not medium["target_reached"]
        and steps == medium["train_steps"] < recipe.medium_max_steps
    ):
        return ["medium"]
    if expert and not expert["target_reached"] and steps < recipe.expert_steps:
        return ["expert"]
    return []


def _reopen_under_larger_budget(
    milestones: dict[str, Any], recipe: CollectRecipe, steps: int, work: Path
) -> dict[str, Any]:
    """Milestones without the reopened ones; their evaluations and rollouts are dropped too."""
    reopened = reopened_milestones(milestones, recipe, steps)
    for name in reopened:
        for stale in work.glob(f"eval-{name}-*.json"):
            stale.unlink()
        for folder in (work / "rollouts").glob(f"{name}-*"):
            for chunk in folder.glob("*.npz"):
                chunk.unlink()
    return {k: v for k, v in milestones.items() if k not in reopened}


def policy_returns(
    task: Task, policy: BehaviourPolicy, episodes: int, seed: int, deterministic: bool
) -> np.ndarray:
    """Returns of a behaviour policy through the one evaluation path every learner uses."""
    rng = np.random.default_rng(seed)
    result = evaluate_policy(
        lambda observations: policy.sample(observations, rng, deterministic),
        task.env_id,
        episodes=episodes,
        seed=seed,
    )
    return np.asarray(result.returns)


def policy_check(
    task: Task,
    recipe: CollectRecipe,
    policy: BehaviourPolicy,
    seed: int,
    stream: str,
    iteration: int,
) -> dict[str, Any]:
    """Evaluate a medium/expert candidate on fresh episodes (own seeds; training is untouched).

    The training return alone overstates a snapshot: it averages episodes of several policies
    and the first crossing of a threshold is a lucky draw (measured: 53 vs 34 normalized).
    """
    check_seed = _stream_seed(seed, stream, 20_000 + iteration)
    returns = policy_returns(
        task, policy, recipe.eval_episodes, check_seed, not recipe.stochastic_rollouts
    )
    mean = float(returns.mean())
    return {"mean": mean, "normalized": task.normalized_score(mean), "seed": check_seed}


BUDGETS = ("medium_max_steps", "expert_steps")


def _targets(recipe: CollectRecipe) -> dict[str, Any]:
    return {
        name: getattr(recipe, name)
        for name in (
            "medium_check_from",
            "medium_range",
            "medium_check_every",
            "medium_max_steps",
            "expert_target",
            "expert_steps",
        )
    }


def _check_same_recipe(state: dict[str, Any], recipe: CollectRecipe, checkpoint: Path) -> None:
    """A work folder belongs to one training recipe: never mix policies of two profiles."""
    found = {**json.loads(state["config"]), **json.loads(state.get("targets", "{}"))}
    # through JSON, as stored, so tuples compare equal to the lists they become
    expected = json.loads(json.dumps({**recipe.trainer_config().to_dict(), **_targets(recipe)}))
    # checkpoints written before targets were recorded are compared on the PPO config alone;
    # budgets may grow (a missed target is then searched on)
    differing = sorted(k for k in found if found[k] != expected.get(k) and k not in BUDGETS)
    if differing:
        raise DataFormatError(
            checkpoint,
            differing[0],
            f"{expected[differing[0]]!r} as in profile '{recipe.profile}' (this work folder was "
            "trained with another recipe: delete it or use another --seed)",
            found[differing[0]],
        )


def medium_replay_block(work: Path, medium_steps: int) -> RolloutBlock:
    """Every PPO transition from step 0 to the medium checkpoint, as one (step, env) block."""
    files = sorted((work / "replay").glob("*.npz"), key=lambda p: int(p.stem))
    blocks, expected = [], 0
    for path in files:
        if int(path.stem) >= medium_steps:
            continue
        if int(path.stem) != expected:
            raise DataFormatError(
                path, "start step", f"{expected} (chunks must be contiguous)", int(path.stem)
            )
        block = _load_block(path)
        blocks.append(block)
        expected += block.rewards.size
    if expected != medium_steps:
        raise DataFormatError(
            work / "replay", "transitions", f"{medium_steps} up to the medium checkpoint", expected
        )
    return _concat_blocks(blocks, 0)


# ---- rollouts and evaluation -----------------------------------------------------------------


def rollout_chunks(
    task: Task,
    recipe: CollectRecipe,
    work: Path,
    seed: int,
    stream: str,
    size: int,
    policy: BehaviourPolicy | None,
    show_progress: bool = True,
) -> tuple[list[RolloutBlock], float, int]:
    """`size` transitions of `policy` (None: uniform random) in chunk files, reusing those on disk.

    Returns the blocks, the seconds spent stepping and the steps stepped in this call.
    """
    folder = (
        work / "rollouts" / f"{stream}-{'stochastic' if recipe.stochastic_rollouts else 'mean'}"
    )
    steps_per_env = -(-recipe.rollout_chunk // recipe.rollout_envs)
    n_chunks = -(-size // (steps_per_env * recipe.rollout_envs))
    per_chunk = steps_per_env * recipe.rollout_envs
    act = _uniform_actions(task) if policy is None else _policy_actions(policy, recipe)
    blocks, seconds, stepped = [], 0.0, 0
    finished: list[float] = []
    with progress(disable=not show_progress) as prog:
        bar = prog.add_task(f"{stream} rollouts", total=n_chunks * per_chunk, rate="", info="")
        for index in range(n_chunks):
            path = folder / f"{index:05d}-{steps_per_env}x{recipe.rollout_envs}.npz"
            if path.exists():
                blocks.append(_load_block(path))
                prog.advance(bar, per_chunk)
                continue
            started = time.perf_counter()

            def on_step(t: int, returns: list[float], started=started, base=index * per_chunk):
                finished.extend(returns)
                if t % 50 == 0 or t == steps_per_env:
                    mean = f"return {np.mean(finished[-100:]):,.0f}" if finished else ""
                    prog.update(
                        bar,
                        completed=base + t * recipe.rollout_envs,
                        rate=rate_text(t * recipe.rollout_envs, time.perf_counter() - started),
                        info=mean,
                    )

            block = run_policy(
                task.env_id,
                act,
                steps_per_env,
                recipe.rollout_envs,
                _stream_seed(seed, stream, index),
                on_step,
            )
            seconds += time.perf_counter() - started
            stepped += block.rewards.size
            save_npz_atomic(path, block.arrays())
            blocks.append(block)
    return blocks, seconds, stepped


def _uniform_actions(task: Task) -> ActionFn:
    space = make_env(task.env_id)[0].action_space
    low, high = space.low.astype(np.float64), space.high.astype(np.float64)
    return lambda obs, rng: rng.uniform(low, high, size=(obs.shape[0], low.size))


def _policy_actions(policy: BehaviourPolicy, recipe: CollectRecipe) -> ActionFn:
    return lambda obs, rng: policy.sample(obs, rng, not recipe.stochastic_rollouts)


def measured_return(
    task: Task, recipe: CollectRecipe, work: Path, seed: int, name: str
) -> dict[str, Any]:
    """The behaviour policy's return over `eval_episodes` fresh episodes, cached beside it."""
    mode = "stochastic" if recipe.stochastic_rollouts else "mean"
    cache = work / f"eval-{name}-{recipe.eval_episodes}-{mode}.json"
    if cache.exists():
        return json.loads(cache.read_text())
    policy, info = load_policy(work / f"policy-{name}.pt")
    eval_seed = _stream_seed(seed, name, 10_000)
    returns = policy_returns(
        task, policy, recipe.eval_episodes, eval_seed, not recipe.stochastic_rollouts
    )
    result = {
        "mean": float(returns.mean()),
        "std": float(returns.std()),
        "normalized": task.normalized_score(float(returns.mean())),
        "episodes": int(returns.size),
        "stochastic": recipe.stochastic_rollouts,
        "seed": eval_seed,
        "training": info,
    }
    write_json_atomic(cache, result)
    return result


# ---- the whole collection --------------------------------------------------------------------


def _episode_return_stats(episodes: list[dict[str, np.ndarray]], task: Task) -> dict[str, Any]:
    """Returns of the dataset's episodes that were not cut by the collection itself."""
    time_limit = make_env(task.env_id)[1]
    complete = [
        float(e["rewards"].sum())
        for e in episodes
        if e["terminations"][-1] or len(e["rewards"]) >= time_limit
    ]
    if not complete:
        return {"episodes": 0}
    mean = float(np.mean(complete))
    return {
        "episodes": len(complete),
        "mean": mean,
        "std": float(np.std(complete)),
        "normalized": task.normalized_score(mean),
    }


def _existing_result(task: Task, path: Path, started: float) -> CollectResult:
    meta = json.loads((path / "data" / "metadata.json").read_text())
    behaviour = meta.get("hipode", {}).get("behaviour_policy", {})
    return CollectResult(
        band=dataset_band(meta),
        dataset_ids=[task.local_dataset_id],
        seconds=time.perf_counter() - started,
        policy_returns={k: v["mean"] for k, v in behaviour.items()},
        normalized_scores={k: v["normalized"] for k, v in behaviour.items()},
        transitions=int(meta.get("total_steps", 0)),
        episodes=int(meta.get("total_episodes", 0)),
        reused=True,
        path=str(path),
    )


def collect(
    task: Task,
    *,
    root: Path | None = None,
    seed: int = 0,
    profile: str = "full",
    force: bool = False,
    show_progress: bool = True,
    allow_off_band: bool = False,
) -> CollectResult:
    """Build the Minari dataset `task.local_dataset_id` (training or reusing its policies).

    An existing dataset is left as it is unless `force`; force rebuilds the dataset from the
    cached policies and chunks (delete `<root>/collect/<env>-seed<seed>/` to retrain).
    A dataset whose behaviour policy misses its band is written, marked so in its metadata,
    and then raises OffBandError (policies and checkpoints stay) unless `allow_off_band`.
    """
    result = _collect(task, root, seed, profile, force, show_progress)
    if result.band and result.band["in_band"] is False and not allow_off_band:
        raise OffBandError(
            f"{task.local_dataset_id} at {result.path}: the behaviour policy "
            f"{off_band_text(result.band)}; the dataset is written and marked off-band in its "
            f"metadata, and augment and train refuse it without {ALLOW_FLAG}. Its policies "
            f"stay in {work_dir(use_datasets_root(root), task.env, seed)}; raise the "
            "training budget (medium_max_steps / expert_steps) in stages/collect.toml and run "
            "this collect again: training goes on from its last checkpoint"
        )
    return result


def _collect(
    task: Task, root: Path | None, seed: int, profile: str, force: bool, show_progress: bool
) -> CollectResult:
    started = time.perf_counter()
    if not task.collectable or task.kind not in POLICIES_BY_KIND:
        raise NotCollectableError(
            f"task '{task.name}' ({task.env_id}, {task.kind}) cannot be collected here: "
            "expected a MuJoCo locomotion task (hopper, halfcheetah, walker2d); "
            f"put its Minari dataset {task.local_dataset_id} in the local store "
            "(`minari download` it where the internet is reachable)"
        )
    root = use_datasets_root(root)
    final = dataset_dir(root, task.local_dataset_id)
    recipe = load_recipe(task.env, profile)
    work = work_dir(root, task.env, seed)
    if final.exists() and not force:
        existing = _existing_result(task, final, started)
        if not (
            existing.band and existing.band["in_band"] is False and _can_search_on(work, recipe)
        ):
            return existing
        # an off-band dataset whose policy search can go on under the grown budget is rebuilt
        force = True
    work.mkdir(parents=True, exist_ok=True)
    # PPO's networks are tiny: a second thread only adds spinning (restored for later stages)
    with work_lock(work), torch_threads(1):
        return _collect_in(task, recipe, root, work, seed, profile, force, show_progress, started)


def _collect_in(
    task: Task,
    recipe: CollectRecipe,
    root: Path,
    work: Path,
    seed: int,
    profile: str,
    force: bool,
    show_progress: bool,
    started: float,
) -> CollectResult:
    """The body of `collect`, run while holding the work folder's lock."""
    needed = POLICIES_BY_KIND[task.kind]
    phases: dict[str, float] = {}
    speeds: dict[str, float] = {}

    milestones: dict[str, Any] = {}
    if needed:
        t0 = time.perf_counter()
        milestones, trained = train_behaviour_policies(
            task, recipe, work, seed, "expert" in needed, show_progress
        )
        phases["train"] = time.perf_counter() - t0
        if trained > 0:
            speeds["train"] = trained / phases["train"]

    t0 = time.perf_counter()
    behaviour = {name: measured_return(task, recipe, work, seed, name) for name in needed}
    phases["evaluate"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    rollout_seconds, rollout_steps = 0.0, 0
    subsampled: dict[str, Any] | None = None
    if task.kind == "medium-replay":
        history = medium_replay_block(work, milestones["medium"]["train_steps"])
        episodes, subsampled = subsample_in_order(
            history, recipe.medium_replay_size, SUBSAMPLE_ABOVE
        )
    else:
        parts = []
        for stream in needed or ("random",):
            policy = load_policy(work / f"policy-{stream}.pt")[0] if stream != "random" else None
            blocks, secs, steps = rollout_chunks(
                task, recipe, work, seed, stream, recipe.rollout_size(stream), policy, show_progress
            )
            rollout_seconds, rollout_steps = rollout_seconds + secs, rollout_steps + steps
            parts.append((blocks, recipe.rollout_size(stream)))
        episodes = []
        for blocks, size in parts:
            episodes += _trim_episodes([e for b in blocks for e in split_episodes(b)], size)
    phases["rollout"] = time.perf_counter() - t0
    if rollout_steps:
        speeds["rollout"] = rollout_steps / rollout_seconds

    t0 = time.perf_counter()
    transitions = int(sum(len(e["rewards"]) for e in episodes))
    band = band_record(task.kind, recipe.bands(), behaviour)
    extra = {
        "hipode": {
            "task": task.name,
            "kind": task.kind,
            "env_id": task.env_id,
            "recipe": recipe.to_dict(),
            "seeds": {
                "seed": seed,
                "trainer": recipe.trainer,
                "trainer_seed": seed,
                "rollouts": {
                    s: [_stream_seed(seed, s, i) for i in range(_n_chunks(recipe, s))]
                    for s in (needed or ("random",))
                    if task.kind != "medium-replay"
                },
                "evaluation": {name: behaviour[name]["seed"] for name in needed},
            },
            "behaviour_policy": behaviour,
            "band": band,
            "dataset_episode_return": _episode_return_stats(episodes, task),
            "medium_replay_subsampled": subsampled,
            "transitions": transitions,
            "training": {
                k: v for k, v in milestones.items() if k in ("medium", "expert", "expert_checks")
            },
            "collect_seconds": {k: round(v, 3) for k, v in phases.items()},
            "versions": package_versions(),
        }
    }
    path = write_minari_dataset(
        task.local_dataset_id,
        episodes,
        env_id=task.env_id,
        root=root,
        staging=work / "staging",
        ref_min_score=task.ref_min_score,
        ref_max_score=task.ref_max_score,
        algorithm_name=recipe.trainer.upper() if needed else "uniform-random",
        description=f"D4RL-style {task.long_name} built by hipode collect "
        f"(profile {profile}, seed {seed})",
        extra_metadata=extra,
        force=force,
    )
    phases["write"] = time.perf_counter() - t0
    return CollectResult(
        dataset_ids=[task.local_dataset_id],
        seconds=time.perf_counter() - started,
        policy_returns={k: v["mean"] for k, v in behaviour.items()},
        normalized_scores={k: v["normalized"] for k, v in behaviour.items()},
        transitions=transitions,
        episodes=len(episodes),
        phase_seconds={k: round(v, 3) for k, v in phases.items()},
        steps_per_second={k: round(v, 1) for k, v in speeds.items()},
        path=str(path),
        band=band,
    )


def _can_search_on(work: Path, recipe: CollectRecipe) -> bool:
    checkpoint = checkpoint_path(work, recipe)
    if not checkpoint.exists():
        return False
    state = load_checkpoint(checkpoint)
    milestones = json.loads(state["milestones"])
    return bool(reopened_milestones(milestones, recipe, int(state["steps"])))


def _n_chunks(recipe: CollectRecipe, stream: str) -> int:
    size = recipe.rollout_size(stream)
    per_chunk = -(-recipe.rollout_chunk // recipe.rollout_envs) * recipe.rollout_envs
    return -(-size // per_chunk)


def subsample_in_order(
    history: RolloutBlock, size: int, above: float
) -> tuple[list[dict[str, np.ndarray]], dict[str, Any] | None]:
    """The history's episodes; if it holds more than `above` x `size` transitions, whole
    episodes evenly spread over training time are kept (in time order) until about `size`.

    Returns the episodes and what was done (None when the whole history is kept)."""
    episodes = split_episodes(history)
    total = history.rewards.size
    if size <= 0 or total <= above * size:
        return episodes, None
    spans = episode_spans(history)
    order = sorted(range(len(episodes)), key=lambda i: (spans[i][1], spans[i][0]))
    fraction, seen, kept_steps, kept = size / total, 0, 0, []
    for i in order:
        seen += len(episodes[i]["rewards"])
        # keep an episode whenever the kept share has fallen behind the target share
        if kept_steps < fraction * seen:
            kept.append(episodes[i])
            kept_steps += len(episodes[i]["rewards"])
    record = {
        "history_transitions": int(total),
        "history_episodes": len(episodes),
        "target_transitions": int(size),
        "kept_transitions": int(kept_steps),
        "kept_episodes": len(kept),
        "rule": "whole episodes in order of their first step, kept whenever the kept share "
        "of transitions so far is below size / history",
    }
    return kept, record


def _trim_episodes(episodes: list[dict[str, np.ndarray]], size: int) -> list[dict[str, np.ndarray]]:
    """Keep exactly `size` transitions: whole episodes, the last one cut and marked truncated."""
    lengths = np.array([len(e["rewards"]) for e in episodes])
    ends = np.cumsum(lengths)
    last = int(np.searchsorted(ends, size))
    kept = episodes[:last]
    room = size - (int(ends[last - 1]) if last else 0)
    if room > 0 and last < len(episodes):
        e = episodes[last]
        truncations = e["truncations"][:room].copy()
        truncations[-1] = not e["terminations"][room - 1]
        kept.append(
            {
                "observations": e["observations"][: room + 1],
                "actions": e["actions"][:room],
                "rewards": e["rewards"][:room],
                "terminations": e["terminations"][:room],
                "truncations": truncations,
            }
        )
    return kept
