"""Policy evaluation: deterministic rollouts in the task's gymnasium env with fixed seeds,
all episodes of all training seeds stepped together so the policies run as one batch, raw
returns and D4RL-normalized scores (reference returns from the data's own metadata)."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass

import numpy as np

from hipode_pipeline.errors import DataFormatError
from hipode_pipeline.simulator import make_env_safely
from hipode_pipeline.tasks import normalized_score

__all__ = [
    "EvalResult",
    "check_data_fits_env",
    "evaluate_policies",
    "evaluate_policy",
    "evaluation_seeds",
    "normalized_score",
]

Policy = Callable[[np.ndarray], np.ndarray]


@dataclass(frozen=True)
class EvalResult:
    """Returns and normalized scores of n evaluation episodes."""

    returns: list[float]  # raw episode returns, in seed order
    lengths: list[int]  # episode lengths
    seeds: list[int]  # reset seed of each episode
    return_mean: float
    return_std: float
    score_mean: float | None  # D4RL-normalized, None without reference returns
    score_std: float | None

    def to_dict(self) -> dict:
        return asdict(self)

    def summary(self) -> dict[str, float | None]:
        """Means and stds only: what metrics lines and score files keep."""
        return {
            "return_mean": self.return_mean,
            "return_std": self.return_std,
            "score_mean": self.score_mean,
            "score_std": self.score_std,
        }


def check_data_fits_env(env_id: str, obs_dim: int, act_dim: int, origin: str) -> None:
    """Refuse data whose observation or action size is not the env's, before any training
    (a policy of the wrong shape would only fail at its first evaluation)."""
    env = make_env_safely(env_id, origin)
    try:
        expected_obs = int(np.prod(env.observation_space.shape))
        expected_act = int(np.prod(env.action_space.shape))
    finally:
        env.close()
    for field, found, expected in (
        ("observations", obs_dim, expected_obs),
        ("actions", act_dim, expected_act),
    ):
        if found != expected:
            raise DataFormatError(origin, field, f"{expected} columns ({env_id}'s layout)", found)


def evaluation_seeds(seed: int, episodes: int) -> list[int]:
    """Fixed, run-independent reset seeds: the same policy always meets the same starts."""
    return [seed * 1000 + i for i in range(episodes)]


def evaluate_policy(
    policy: Policy,
    env_id: str,
    *,
    episodes: int = 10,
    seed: int = 0,
    ref_min_score: float | None = None,
    ref_max_score: float | None = None,
    max_episode_steps: int | None = None,
) -> EvalResult:
    """Run `episodes` deterministic episodes side by side; `policy` maps (n, ds) -> (n, da)."""
    return evaluate_policies(
        lambda observations: np.asarray(policy(observations[0]))[None],
        env_id,
        episodes=episodes,
        seeds=[seed],
        ref_min_score=ref_min_score,
        ref_max_score=ref_max_score,
        max_episode_steps=max_episode_steps,
    )[0]


def evaluate_policies(
    policies: Callable[[np.ndarray], np.ndarray],
    env_id: str,
    *,
    episodes: int,
    seeds: Sequence[int],
    ref_min_score: float | None = None,
    ref_max_score: float | None = None,
    max_episode_steps: int | None = None,
) -> list[EvalResult]:
    """K policies (one per training seed) at once, policy k on the evaluation starts of seed k
    (those a run of that seed alone meets); `policies` maps (K, n, ds) -> (K, n, da)."""
    starts = [evaluation_seeds(seed, episodes) for seed in seeds]
    k = len(starts)
    envs = [[make_env_safely(env_id) for _ in range(episodes)] for _ in range(k)]
    low, high = envs[0][0].action_space.low, envs[0][0].action_space.high
    try:
        observations = np.stack(
            [
                [env.reset(seed=s)[0] for env, s in zip(row, row_starts, strict=True)]
                for row, row_starts in zip(envs, starts, strict=True)
            ]
        ).astype(np.float32)
        returns = np.zeros((k, episodes))
        lengths = np.zeros((k, episodes), dtype=np.int64)
        active = np.ones((k, episodes), dtype=bool)
        while active.any():
            # only episodes still running anywhere: a policy that samples draws no numbers for
            # finished ones (with one seed, exactly the episodes still running)
            columns = np.flatnonzero(active.any(0))
            # the env charges control cost on the action as given: keep it inside the limits
            actions = np.clip(np.asarray(policies(observations[:, columns])), low, high)
            for g, c in zip(*np.nonzero(active[:, columns]), strict=True):
                i = columns[c]
                obs, reward, terminated, truncated, _ = envs[g][i].step(actions[g, c])
                observations[g, i] = obs
                returns[g, i] += float(reward)
                lengths[g, i] += 1
                if (
                    terminated
                    or truncated
                    or (max_episode_steps is not None and lengths[g, i] >= max_episode_steps)
                ):
                    active[g, i] = False
    finally:
        for row in envs:
            for env in row:
                env.close()
    return [
        _result(returns[g], lengths[g], starts[g], ref_min_score, ref_max_score) for g in range(k)
    ]


def _result(returns, lengths, seeds, ref_min_score, ref_max_score) -> EvalResult:
    scores = None
    if ref_min_score is not None and ref_max_score is not None:
        scores = normalized_score(returns, ref_min_score, ref_max_score)
    return EvalResult(
        returns=returns.tolist(),
        lengths=lengths.tolist(),
        seeds=list(seeds),
        return_mean=float(returns.mean()),
        return_std=float(returns.std()),
        score_mean=None if scores is None else float(scores.mean()),
        score_std=None if scores is None else float(scores.std()),
    )
