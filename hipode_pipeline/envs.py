"""Environment-specific facts stage one needs: each MuJoCo env's own termination rule, applied to
observations, so a synthetic transition ends exactly where the real environment would end it.

The locomotion rules mirror gymnasium's v5 `is_healthy` with default constructor arguments and
the default observation layout (x position excluded, so observation[0] is the torso height and
observation[1] its angle). The Adroit hands of gymnasium-robotics (v1) never terminate: their
`step` always returns terminated = False and episodes end by the time limit only.

Also the one map from env ids met in data (D4RL dataset names, older gym versions) to the
Gymnasium env we run: `canonical_env_id`.
"""

from __future__ import annotations

import re
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from hipode_pipeline.errors import DataFormatError
from hipode_pipeline.tasks import MUJOCO_ENVS, all_tasks


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

# Adroit hands (gymnasium-robotics, the `adroit` extra): observation sizes of the v1 envs
ADROIT_ID_PREFIX = "AdroitHand"
ADROIT_OBS_DIM = {
    "AdroitHandPen": 45,
    "AdroitHandDoor": 39,
    "AdroitHandHammer": 46,
    "AdroitHandRelocate": 39,
}
# observation columns of each family's default layout
OBS_DIM = {
    "Hopper": HOPPER.obs_dim,
    "Walker2d": WALKER2D.obs_dim,
    "HalfCheetah": HALFCHEETAH_OBS_DIM,
    **ADROIT_OBS_DIM,
}
NEVER_TERMINATING_FAMILIES = ("HalfCheetah", *ADROIT_OBS_DIM)
TERMINATION_FAMILIES = tuple(OBS_DIM)
KNOWN_ENV_IDS = (
    *(f"{family}-v5" for family in ("Hopper", "Walker2d", "HalfCheetah")),
    *(f"{family}-v1" for family in ADROIT_OBS_DIM),
)


def env_family(env_id: str) -> str:
    """'Hopper-v5' -> 'Hopper' (the rules are the same for every version of a family)."""
    return env_id.split("-v")[0]


def termination_rule(
    env_id: str | None, obs_dim: int, origin: str = "source"
) -> Callable[[np.ndarray], np.ndarray]:
    """`env_id`'s own termination rule: (M, obs_dim) raw observations -> (M,) bool.

    HalfCheetah and the Adroit hands never terminate. An unknown env or an observation size other
    than the default layout raises DataFormatError naming `origin`, since a wrong rule would
    silently corrupt the synthetic data's terminal flags.
    """
    family = env_family(env_id or "")
    if family not in TERMINATION_FAMILIES:
        raise DataFormatError(
            origin,
            "env_id",
            f"a MuJoCo env with a known termination rule ({', '.join(KNOWN_ENV_IDS)})",
            env_id,
        )
    expected_dim = OBS_DIM[family]
    if obs_dim != expected_dim:
        raise DataFormatError(
            origin,
            "observations",
            f"{expected_dim} columns ({env_id}'s default observation layout"
            + (")" if family in ADROIT_OBS_DIM else " without the x position)"),
            obs_dim,
        )
    if family in NEVER_TERMINATING_FAMILIES:
        return lambda observations: np.zeros(len(observations), dtype=np.bool_)
    return (HOPPER if family == "Hopper" else WALKER2D).terminal


def terminal_flags(
    env_id: str | None, next_observations: np.ndarray, origin: str = "source"
) -> np.ndarray:
    """Apply `env_id`'s termination rule to (M, obs_dim) raw next observations -> (M,) bool."""
    return termination_rule(env_id, next_observations.shape[1], origin)(next_observations)


# D4RL's dataset kinds: hopper-medium-replay-v2 (locomotion), pen-human-v1 (Adroit)
D4RL_LOCOMOTION_KINDS = (
    "random",
    "medium",
    "medium-replay",
    "medium-expert",
    "expert",
    "full-replay",
)
D4RL_ADROIT_KINDS = ("human", "cloned", "expert")
D4RL_NAME = re.compile(r"([a-z0-9]+)-([a-z]+(?:-[a-z]+)*)-v\d+", re.IGNORECASE)
# gym's Hopper-v2/v3 (mujoco-py) and gymnasium's v4, and v5 itself spelled in another case
OLD_LOCOMOTION_ID = re.compile(r"([a-z0-9]+)-v([2-5])", re.IGNORECASE)


def canonical_env_id(raw: str) -> tuple[str, str | None]:
    """The env we run for an env id met in data, and a one-line note when it is another id.

    D4RL dataset names (hopper-medium-replay-v2, pen-human-v1) and older versions of the
    locomotion envs (Hopper-v2..v4) map to the registry's env of their family (Hopper-v5,
    AdroitHandPen-v1); anything else is returned unchanged, to be checked by the caller.
    """
    text = raw.strip()
    # family -> the env the task registry runs it on, e.g. hopper -> Hopper-v5
    family_env = {task.env: task.env_id for task in all_tasks().values()}
    # D4RL's locomotion data came from the v2 envs, and v2-v5 of these three families share the
    # default observation layout (x position excluded), so such data is v5 data
    d4rl = D4RL_NAME.fullmatch(text)
    if d4rl:
        family, kind = d4rl.group(1).lower(), d4rl.group(2).lower()
        kinds = D4RL_LOCOMOTION_KINDS if family in MUJOCO_ENVS else D4RL_ADROIT_KINDS
        if family in family_env and kind in kinds:
            target = family_env[family]
            return target, f"env id {raw!r} is a D4RL dataset name; running it as {target}"
    old = OLD_LOCOMOTION_ID.fullmatch(text)
    if old and old.group(1).lower() in MUJOCO_ENVS:
        target = family_env[old.group(1).lower()]
        if target == raw:
            return raw, None
        if old.group(2) == target.rsplit("-v", 1)[1]:
            return target, f"env id {raw!r} is spelled {target} in gymnasium; running it as that"
        return target, f"env id {raw!r} is an older version; running it as {target}"
    return raw, None
