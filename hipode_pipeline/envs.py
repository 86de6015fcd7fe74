"""Environment-specific facts stage one needs: each MuJoCo env's own termination rule, applied to
observations, so a synthetic transition ends exactly where the real environment would end it.

The rules mirror gymnasium's v5 `is_healthy` with default constructor arguments and the default
observation layout (x position excluded, so observation[0] is the torso height and
observation[1] its angle).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from hipode_pipeline.errors import DataFormatError


@dataclass(frozen=True)
class HealthyRanges:
    """An env's healthy region on its observation; outside it the episode terminates."""

    obs_dim: int  # observation size of the default layout (x position excluded)
    z_range: tuple[float, float]  # open interval for the torso height, observation[0]
    angle_range: tuple[float, float]  # open interval for the torso angle, observation[1]
    state_range: tuple[float, float] | None  # open interval for every observation[1:], or None

    def terminal(self, observations: np.ndarray) -> np.ndarray:
        """(M, obs_dim) raw observations -> (M,) bool: True where the env would terminate."""
        z, angle = observations[:, 0], observations[:, 1]
        healthy = (self.z_range[0] < z) & (z < self.z_range[1])
        healthy &= (self.angle_range[0] < angle) & (angle < self.angle_range[1])
        if self.state_range is not None:
            # gymnasium checks unclipped qvel; observations hold velocities clipped to [-10, 10],
            # which is all a synthetic state has, and they never reach the +-100 bound
            rest = observations[:, 1:]
            healthy &= ((self.state_range[0] < rest) & (rest < self.state_range[1])).all(axis=1)
        return ~healthy


# gymnasium 1.x Hopper-v5 / Walker2d-v5 defaults (the v2-v4 envs use the same numbers)
HOPPER = HealthyRanges(
    obs_dim=11, z_range=(0.7, float("inf")), angle_range=(-0.2, 0.2), state_range=(-100.0, 100.0)
)
WALKER2D = HealthyRanges(obs_dim=17, z_range=(0.8, 2.0), angle_range=(-1.0, 1.0), state_range=None)
HALFCHEETAH_OBS_DIM = 17

TERMINATION_FAMILIES = ("Hopper", "Walker2d", "HalfCheetah")
KNOWN_ENV_IDS = tuple(f"{family}-v5" for family in TERMINATION_FAMILIES)


def env_family(env_id: str) -> str:
    """'Hopper-v5' -> 'Hopper' (the rules are the same for every version of a family)."""
    return env_id.split("-v")[0]


def termination_rule(
    env_id: str | None, obs_dim: int, origin: str = "source"
) -> Callable[[np.ndarray], np.ndarray]:
    """`env_id`'s own termination rule: (M, obs_dim) raw observations -> (M,) bool.

    HalfCheetah never terminates. An unknown env or an observation size other than the default
    layout raises DataFormatError naming `origin`, since a wrong rule would silently corrupt the
    synthetic data's terminal flags.
    """
    family = env_family(env_id or "")
    if family not in TERMINATION_FAMILIES:
        raise DataFormatError(
            origin,
            "env_id",
            f"a MuJoCo env with a known termination rule ({', '.join(KNOWN_ENV_IDS)})",
            env_id,
        )
    expected_dim = {
        "Hopper": HOPPER.obs_dim,
        "Walker2d": WALKER2D.obs_dim,
        "HalfCheetah": HALFCHEETAH_OBS_DIM,
    }[family]
    if obs_dim != expected_dim:
        raise DataFormatError(
            origin,
            "observations",
            f"{expected_dim} columns ({env_id}'s default layout without the x position)",
            obs_dim,
        )
    if family == "HalfCheetah":
        return lambda observations: np.zeros(len(observations), dtype=np.bool_)
    return (HOPPER if family == "Hopper" else WALKER2D).terminal


def terminal_flags(
    env_id: str | None, next_observations: np.ndarray, origin: str = "source"
) -> np.ndarray:
    """Apply `env_id`'s termination rule to (M, obs_dim) raw next observations -> (M,) bool."""
    return termination_rule(env_id, next_observations.shape[1], origin)(next_observations)
