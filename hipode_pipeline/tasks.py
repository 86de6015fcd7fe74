"""Task registry: the paper's tasks by short and long name, with env ids, reference scores and
per-learner hyper-parameters. The data lives in stages/tasks.toml and stages/defaults.toml."""

from __future__ import annotations

import difflib
import functools
import tomllib
from dataclasses import dataclass, field

from hipode_pipeline.errors import UnknownTaskError
from hipode_pipeline.paths import stages_dir

KIND_ABBREVIATIONS = {
    "r": "random",
    "m": "medium",
    "m-r": "medium-replay",
    "m-e": "medium-expert",
    "e": "expert",
    "h": "human",
}
LEARNERS = ("td3bc", "cql", "iql")
MUJOCO_ENVS = ("hopper", "halfcheetah", "walker2d")


def normalized_score(episode_return, ref_min: float, ref_max: float):
    """D4RL's 100 · (R − R_random) / (R_expert − R_random): 0 a random policy, 100 an expert."""
    return 100.0 * (episode_return - ref_min) / (ref_max - ref_min)


@dataclass(frozen=True)
class AugmentParams:
    """HIPODE's hyper-parameters for one (task, learner) pair, as the paper's tables give them."""

    eta: float  # synthetic rate
    lam: float  # selecting rate
    n: int  # candidates per source state
    alpha: float  # negative-sampling penalty weight
    sigma: float  # negative-sampling scope (z-scored units)
    learner_alpha: float | None  # the learner's own alpha (TD3+BC, CQL); None for IQL
    from_paper: bool  # False when the paper gives no values for this pair and defaults apply


@dataclass(frozen=True)
class Task:
    """One offline-RL task: an environment family and a dataset kind."""

    name: str  # short name, e.g. hopper-m-r
    env: str  # family, e.g. hopper
    kind: str  # random | medium | medium-replay | medium-expert | expert | human
    env_id: str  # gymnasium id, e.g. Hopper-v5
    ref_min_score: float  # D4RL's random-policy return
    ref_max_score: float  # D4RL's expert return
    params: dict[str, AugmentParams] = field(repr=False)
    # evaluation horizon when D4RL's is shorter than the registered env's (pen: 100), else None
    max_episode_steps: int | None = None

    @property
    def long_name(self) -> str:
        return f"{self.env}-{self.kind}"

    @property
    def local_dataset_id(self) -> str:
        """The Minari id of this task's source in the local store: the one `hipode collect`
        writes, or for data that cannot be collected here (Adroit's human demonstrations),
        Minari's own id of D4RL's dataset (D4RL/pen/human-v2)."""
        if not self.collectable:
            return f"D4RL/{self.env}/{self.kind}-v2"
        return f"local/{self.env}/{self.kind}-v0"

    @property
    def collectable(self) -> bool:
        """Whether `hipode collect` can build this task's data here (MuJoCo locomotion only)."""
        return self.env in MUJOCO_ENVS

    def augment_params(self, learner: str = "td3bc") -> AugmentParams:
        if learner not in self.params:
            raise UnknownTaskError(
                f"unknown learner '{learner}' for task {self.name}; "
                f"expected one of {sorted(self.params)}"
            )
        return self.params[learner]

    def normalized_score(self, episode_return: float) -> float:
        """D4RL-normalized score with this task's reference returns."""
        return normalized_score(episode_return, self.ref_min_score, self.ref_max_score)


def _load_toml(name: str) -> dict:
    with open(stages_dir() / name, "rb") as f:
        return tomllib.load(f)


@functools.cache
def all_tasks() -> dict[str, Task]:
    """Every registered task by short name, in the order of stages/tasks.toml."""
    data, defaults = _load_toml("tasks.toml"), _load_toml("defaults.toml")
    base, learner_defaults = defaults["augment"], defaults.get("learners", {})
    tasks = {}
    for name, spec in data["tasks"].items():
        env = data["envs"][spec["env"]]
        params = {}
        for learner in (*LEARNERS, "iql_v2"):
            given = spec.get(learner)
            if given is None and learner == "iql_v2":
                continue
            values = {
                **base,
                **learner_defaults.get(learner.removesuffix("_v2"), {}),
                **(given or {}),
            }
            params[learner] = AugmentParams(
                eta=float(values["eta"]),
                lam=float(values["lam"]),
                n=int(values["n"]),
                alpha=float(values["alpha"]),
                sigma=float(values["sigma"]),
                learner_alpha=values.get("learner_alpha"),
                from_paper=given is not None,
            )
        tasks[name] = Task(
            name=name,
            env=spec["env"],
            kind=spec["kind"],
            env_id=env["env_id"],
            ref_min_score=float(env["ref_min_score"]),
            ref_max_score=float(env["ref_max_score"]),
            params=params,
            max_episode_steps=env.get("max_episode_steps"),
        )
    return tasks


def get_task(name: str) -> Task:
    """A task by short (hopper-m-r) or long (hopper-medium-replay) name; -v0/-v2 optional."""
    tasks = all_tasks()
    key = name.strip().lower().removesuffix("-v0").removesuffix("-v2")
    if key in tasks:
        return tasks[key]
    by_long = {t.long_name: t for t in tasks.values()}
    if key in by_long:
        return by_long[key]
    names = [*tasks, *by_long]
    close = difflib.get_close_matches(key, names, n=5, cutoff=0.5)
    hint = f"; did you mean {', '.join(close)}?" if close else f"; known tasks: {', '.join(tasks)}"
    raise UnknownTaskError(f"unknown task '{name}'{hint}")
