"""Where synthetic transitions lose authenticity, stage by stage, judged by the simulator.

All errors use `verify`'s next-state error: the mean over dimensions of |x - y| / the source's
next-state std ("source stds per dimension"). For the kept synthetic rows (s, a~, s~'), with
s* = simulator(s, a~) and f(s, a~) the dynamics ensemble's mean prediction (its elites when set):
- total: error(s~', s*), what `verify` reports;
- ensemble on kept rows: error(f(s, a~), s*), how wrong the dynamics check's own model is where
  it is asked to judge (the check cannot see errors smaller than this);
- check distance: error(f(s, a~), s~'), what the check ranked by (in verify's metric).
On held-out real transitions (s, a, s'), rows the generators never trained on:
- inverse action: error(simulator(s, inverse_action(s, s')), s'), how well the inverse model
  reaches a next state that is reachable; the recorded action's own error(simulator(s, a), s')
  is the floor (velocity clipping in the observation, solver start);
- ensemble one step (MOPO-style model error): per dimension the mean of |f(s, a) - s'| / std,
  their mean, and the reward's mean |f_r(s, a) - r| / reward std.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from hipode_pipeline.data.transitions import Transitions
from hipode_pipeline.models import training
from hipode_pipeline.models.generators import Generators
from hipode_pipeline.seeding import derive_seed
from hipode_pipeline.simulator import clipped_velocity_rows, step_from_observations

# added to the source stds before dividing, so a constant dimension stays finite
STD_EPS = 1e-6
# novelty bins of the matched comparison (quantiles of HIPODE's and the baseline's novelty)
NOVELTY_BINS = 5


def state_errors(a: np.ndarray, b: np.ndarray, std: np.ndarray) -> np.ndarray:
    """(K,) mean over dimensions of |a - b| / std; non-finite rows are infinitely wrong."""
    error = (np.abs(np.asarray(a, np.float64) - np.asarray(b, np.float64)) / (std + STD_EPS)).mean(
        axis=1
    )
    return np.where(np.isfinite(error), error, np.inf)


def one_step_errors(predicted: np.ndarray, recorded: np.ndarray, std: np.ndarray) -> dict:
    """A model's next states against recorded ones: the spread of `state_errors` over rows and
    the mean error per dimension (same units)."""
    per_dim = (np.abs(np.asarray(predicted, np.float64) - recorded) / (std + STD_EPS)).mean(axis=0)
    return {
        **spread(state_errors(predicted, recorded, std)),
        "per_dimension": [round(float(x), 6) for x in per_dim],
    }


def spread(values: np.ndarray) -> dict[str, float]:
    values = np.asarray(values, np.float64)
    return {
        "median": float(np.median(values)),
        "mean": float(values.mean()),
        "p90": float(np.quantile(values, 0.9)),
    }


def _ensemble_mean(generators: Generators, states: np.ndarray, actions: np.ndarray):
    """The dynamics ensemble's mean next state (raw units) and reward for raw (s, a) rows."""
    device = generators.device
    with torch.no_grad():
        states_norm = generators.normalizer.normalize(torch.as_tensor(states, device=device))
        next_norm, rewards = generators.dynamics.sample(
            states_norm, torch.as_tensor(actions, device=device), use_mean=True
        )
    next_states = generators.normalizer.denormalize(next_norm.float().cpu().numpy())
    return next_states.astype(np.float64), rewards.float().cpu().numpy().astype(np.float64)


def _inverse_actions(generators: Generators, states: np.ndarray, next_states: np.ndarray, seed):
    device = generators.device
    sampling = torch.Generator(device=device).manual_seed(derive_seed(seed, "diagnose-inverse"))
    with torch.no_grad():
        pair = torch.cat(
            [
                generators.normalizer.normalize(torch.as_tensor(states, device=device)),
                generators.normalizer.normalize(torch.as_tensor(next_states, device=device)),
            ],
            dim=1,
        )
        actions = generators.inverse_action.sample(pair, 1, generator=sampling)[:, 0]
    return actions.float().cpu().numpy()


def stage_diagnosis(
    generators: Generators,
    env_id: str,
    synthetic: Transitions,
    simulated_next: np.ndarray,
    source: Transitions,
    *,
    next_state_std: np.ndarray,
    reward_std: float,
    generator_seed: int,
    sample: int,
    seed: int,
    origin: str,
) -> dict[str, Any]:
    """The per-stage errors of the module doc: kept rows and held-out real rows, in units of
    the source's next-state stds (`next_state_std`) and reward std."""
    std = next_state_std
    predicted, _ = _ensemble_mean(generators, synthetic.observations, synthetic.actions)
    kept = {
        "total": spread(state_errors(synthetic.next_observations, simulated_next, std)),
        "ensemble_on_kept_rows": spread(state_errors(predicted, simulated_next, std)),
        "check_distance": spread(state_errors(predicted, synthetic.next_observations, std)),
    }
    # the rows the generators of that seed never trained on
    _, heldout = training.split_rows(
        len(source), generators.config.heldout_fraction, generator_seed
    )
    rows = np.sort(heldout.numpy())
    rng = np.random.default_rng(derive_seed(seed, "diagnose-heldout"))
    rows = np.sort(rng.choice(rows, size=min(sample, len(rows)), replace=False))
    states, actions = source.observations[rows], source.actions[rows]
    next_states, rewards = source.next_observations[rows], source.rewards[rows]
    inverse = _inverse_actions(generators, states, next_states, seed)
    both = step_from_observations(
        env_id,
        np.concatenate([states, states]),
        np.concatenate([inverse, actions]).astype(np.float64),
        origin=origin,
    )[0]
    reached_inverse, reached_recorded = both[: len(rows)], both[len(rows) :]
    model_next, model_rewards = _ensemble_mean(generators, states, actions)
    clipped = clipped_velocity_rows(env_id, states)
    return {
        "kept": kept,
        "heldout_rows": int(len(rows)),
        "inverse_action_on_real": spread(state_errors(reached_inverse, next_states, std)),
        "recorded_action_on_real": spread(state_errors(reached_recorded, next_states, std)),
        "ensemble_one_step_on_real": {
            **one_step_errors(model_next, next_states, std),
            "reward_mean_abs_error_in_stds": float(
                np.abs(model_rewards - rewards).mean() / (reward_std + STD_EPS)
            ),
            "elites": generators.dynamics.elites,
        },
        "heldout_clipped_share": float(clipped.mean()),
    }


def matched_novelty(
    hipode_novelty: np.ndarray,
    hipode_error: np.ndarray,
    baseline_novelty: np.ndarray,
    baseline_error: np.ndarray,
    bins: int = NOVELTY_BINS,
) -> dict[str, Any]:
    """Median errors of HIPODE and the baseline in shared novelty bins (quantiles of both), and
    the median over bins holding both of HIPODE's median / the baseline's."""
    pooled = np.concatenate([hipode_novelty, baseline_novelty])
    edges = np.quantile(pooled, np.linspace(0, 1, bins + 1))
    edges[-1] = np.inf
    table, ratios = [], []
    for low, high in zip(edges[:-1], edges[1:], strict=True):
        mine = (hipode_novelty >= low) & (hipode_novelty < high)
        theirs = (baseline_novelty >= low) & (baseline_novelty < high)
        row: dict[str, Any] = {
            "novelty_from": float(low),
            "novelty_to": None if np.isinf(high) else float(high),
            "hipode_n": int(mine.sum()),
            "baseline_n": int(theirs.sum()),
            "hipode_median": float(np.median(hipode_error[mine])) if mine.any() else None,
            "baseline_median": float(np.median(baseline_error[theirs])) if theirs.any() else None,
        }
        if row["hipode_median"] is not None and row["baseline_median"]:
            ratios.append(row["hipode_median"] / row["baseline_median"])
        table.append(row)
    return {
        "bins": table,
        "median_ratio": float(np.median(ratios)) if ratios else None,
        "bins_compared": len(ratios),
    }
