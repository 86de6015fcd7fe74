"""The MuJoCo simulator as ground truth: build an env from an id that came from a file without
running foreign code, put it into the state an observation describes, and step it.

Observations of the supported envs (gymnasium v5, default layout) omit the x position; their
dynamics and rewards do not depend on it, so it is restored as 0: qpos = [0, obs[:nq-1]],
qvel = obs[nq-1:].
"""

from __future__ import annotations

import contextlib
import io
from pathlib import Path

import gymnasium as gym
import mujoco
import numpy as np

from hipode_pipeline.envs import ADROIT_ID_PREFIX, env_family
from hipode_pipeline.errors import DataFormatError, HipodeError, MissingExtraError, UnsafeEnvError

# only environments implemented by gymnasium itself, or gymnasium-robotics' Adroit hands (the
# `adroit` extra), are ever constructed
SAFE_ENTRY_POINT_PREFIXES = ("gymnasium.envs.", "gymnasium_robotics.envs.adroit_hand.")
# env families whose observation is [qpos[1:], qvel] (x position excluded)
RESTORABLE_FAMILIES = ("Hopper", "Walker2d", "HalfCheetah")
# Hopper and Walker2d clip the velocities in their observation to this bound; HalfCheetah does not
CLIPPED_VELOCITY_BOUND = {"Hopper": 10.0, "Walker2d": 10.0, "HalfCheetah": None}
# velocities (nv) are the trailing columns of the observation
VELOCITY_DIMS = {"Hopper": 6, "Walker2d": 9, "HalfCheetah": 9}


def check_env_id(env_id: object, origin: str | Path | None = None) -> gym.envs.registration.EnvSpec:
    """The registered spec of `env_id` when gymnasium itself implements it; otherwise raise,
    without importing or calling anything the id names.

    `origin` is the file the id was read from: the error is then a DataFormatError naming it and
    the field "env_id".
    """
    expected = (
        "the id of an environment registered by gymnasium itself or an Adroit env of "
        f"gymnasium-robotics (entry point under {' or '.join(SAFE_ENTRY_POINT_PREFIXES)}), "
        "e.g. Hopper-v5"
    )
    problem: str | None = None
    spec = None
    if not isinstance(env_id, str) or not env_id:
        problem = "not a non-empty string"
    elif ":" in env_id:
        # gym.make would import the module named before the colon
        problem = "a module path"
    else:
        register_adroit_envs(env_id)
        spec = gym.envs.registry.get(env_id)
        if spec is None:
            problem = "not registered"
        elif not (
            isinstance(spec.entry_point, str)
            and spec.entry_point.startswith(SAFE_ENTRY_POINT_PREFIXES)
        ):
            problem = f"registered with a foreign entry point {spec.entry_point!r}"
    if problem is None:
        return spec
    if origin is not None:
        raise DataFormatError(origin, "env_id", expected, f"{env_id!r} ({problem})")
    raise UnsafeEnvError(f"env id {env_id!r} refused ({problem}): expected {expected}")


def register_adroit_envs(env_id: str) -> None:
    """Register gymnasium-robotics' envs when `env_id` is an Adroit hand not yet registered.

    Raises MissingExtraError when the `adroit` extra (gymnasium-robotics) is not installed.
    """
    if not env_id.startswith(ADROIT_ID_PREFIX) or env_id in gym.envs.registry:
        return
    try:
        # its import prints a notice on every process that door, hammer and relocate's dense
        # rewards changed in 1.2.1 (the README says so once)
        with contextlib.redirect_stderr(io.StringIO()):
            import gymnasium_robotics
    except ImportError:
        raise MissingExtraError(
            f"env {env_id} is an Adroit hand of gymnasium-robotics, which is not installed; "
            "install the optional extra: pip install -e '.[adroit]'"
        ) from None
    gym.register_envs(gymnasium_robotics)


def make_env_safely(env_id: str, origin: str | Path | None = None) -> gym.Env:
    """Build `env_id` after `check_env_id` accepted it (from its vetted spec, not the string)."""
    spec = check_env_id(env_id, origin)
    return gym.make(spec)


def make_restorable_env(env_id: str, origin: str | Path | None = None) -> gym.Env:
    """A safely built env of a family whose state an observation fully describes (x aside)."""
    if env_family(str(env_id)) not in RESTORABLE_FAMILIES:
        check_env_id(env_id, origin)
        raise DataFormatError(
            origin or "env_id",
            "env_id",
            f"an env of the families {RESTORABLE_FAMILIES} (their v5 observation layout)",
            env_id,
        )
    env = make_env_safely(env_id, origin)
    env.reset(seed=0)
    return env


def set_state_from_observation(env: gym.Env, observation: np.ndarray) -> None:
    """Put a MuJoCo env into the state `observation` (default v5 layout) describes, x = 0.

    Velocities the env clipped in its observation cannot be recovered; they are set as observed.
    """
    raw = env.unwrapped
    nq, nv = int(raw.model.nq), int(raw.model.nv)
    observation = np.asarray(observation, dtype=np.float64)
    if observation.shape != (nq - 1 + nv,):
        raise DataFormatError(
            "observations",
            "shape",
            f"({nq - 1 + nv},) for {raw.spec.id if raw.spec else type(raw).__name__} "
            "(default layout without the x position)",
            observation.shape,
        )
    data = raw.data
    data.qpos[0] = 0.0
    data.qpos[1:] = observation[: nq - 1]
    data.qvel[:] = observation[nq - 1 :]
    # a fresh solver start per row, so a row's result does not depend on the row before it
    data.qacc_warmstart[:] = 0.0
    mujoco.mj_forward(raw.model, data)


def step_from_observations(
    env_id: str,
    observations: np.ndarray,
    actions: np.ndarray,
    *,
    origin: str | Path | None = None,
    progress_callback=None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Step the simulator once from each (observation, action) row.

    Returns next observations (M, obs_dim) float64, rewards (M,) float64 and the env's own
    terminated flags (M,) bool. `progress_callback(rows_done)` is called every 256 rows.
    """
    observations = np.asarray(observations, dtype=np.float64)
    actions = np.asarray(actions, dtype=np.float64)
    env = make_restorable_env(env_id, origin)
    # the unwrapped env: no time limit or call-order checks between restored states
    raw = env.unwrapped
    model, data = raw.model, raw.data
    nq, obs_dim = int(model.nq), int(model.nq - 1 + model.nv)
    act_dim = int(np.prod(raw.action_space.shape))
    rows = len(observations)
    try:
        if observations.ndim != 2 or observations.shape[1] != obs_dim:
            raise DataFormatError(
                origin or "observations",
                "observations",
                f"(M, {obs_dim}) rows for {env_id}",
                observations.shape,
            )
        if actions.shape != (rows, act_dim):
            raise DataFormatError(
                origin or "actions",
                "actions",
                f"({rows}, {act_dim}) rows for {env_id}",
                actions.shape,
            )
        next_observations = np.empty((rows, obs_dim), dtype=np.float64)
        rewards = np.empty(rows, dtype=np.float64)
        terminated = np.empty(rows, dtype=np.bool_)
        for row in range(rows):
            # set_state_from_observation inlined: this loop is the hot path
            data.qpos[0] = 0.0
            data.qpos[1:] = observations[row, : nq - 1]
            data.qvel[:] = observations[row, nq - 1 :]
            data.qacc_warmstart[:] = 0.0
            mujoco.mj_forward(model, data)
            next_observations[row], rewards[row], terminated[row], _, _ = raw.step(actions[row])
            if progress_callback is not None and (row + 1) % 256 == 0:
                progress_callback(row + 1)
    finally:
        env.close()
    if progress_callback is not None:
        progress_callback(rows)
    return next_observations, rewards, terminated


def policy_returns(
    env_id: str,
    observations: np.ndarray,
    policy,
    *,
    horizon: int,
    discount: float,
    origin: str | Path | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """The discounted return of `policy` from each observation's state, by running it in the
    simulator for up to `horizon` steps (a fall ends the return; the time limit does not apply).

    `policy` maps (n, obs_dim) observations to (n, act_dim) actions, called once per step for
    every start still running. Returns the returns (M,) float64 and the steps run (M,) int.
    A start whose velocities sit at the env's clipping bound (`clipped_velocity_rows`) is not
    restored exactly; leave those out where exact returns matter.
    """
    observations = np.asarray(observations, dtype=np.float64)
    if horizon < 1 or not 0.0 < discount <= 1.0:
        raise HipodeError(
            f"policy_returns: expected horizon ≥ 1 and discount in (0, 1], found "
            f"{horizon} and {discount}"
        )
    if not len(observations):
        return np.zeros(0), np.zeros(0, dtype=np.int64)
    envs = [make_restorable_env(env_id, origin) for _ in range(len(observations))]
    try:
        raw = [env.unwrapped for env in envs]  # no time limit between restored states
        for env, observation in zip(envs, observations, strict=True):
            set_state_from_observation(env, observation)
        low, high = raw[0].action_space.low, raw[0].action_space.high
        current = observations.astype(np.float32)  # what a policy sees: float32, as stored
        returns = np.zeros(len(envs))
        steps = np.zeros(len(envs), dtype=np.int64)
        active = np.ones(len(envs), dtype=bool)
        weight = 1.0
        for _ in range(horizon):
            running = np.flatnonzero(active)
            if not len(running):
                break
            # the env charges control cost on the action as given: keep it inside the limits
            actions = np.clip(np.asarray(policy(current[running]), np.float64), low, high)
            for i, action in zip(running, actions, strict=True):
                current[i], reward, terminated, _, _ = raw[i].step(action)
                returns[i] += weight * float(reward)
                steps[i] += 1
                active[i] = not terminated
            weight *= discount
    finally:
        for env in envs:
            env.close()
    return returns, steps


def clipped_velocity_rows(env_id: str, observations: np.ndarray) -> np.ndarray:
    """(M,) bool: rows whose observed velocities sit at the env's clipping bound, so the true
    state (and hence the simulator's answer) is uncertain."""
    bound = CLIPPED_VELOCITY_BOUND.get(env_family(env_id))
    if bound is None:
        return np.zeros(len(observations), dtype=np.bool_)
    velocities = np.asarray(observations)[:, -VELOCITY_DIMS[env_family(env_id)] :]
    return (np.abs(velocities) >= bound - 1e-6).any(axis=1)
