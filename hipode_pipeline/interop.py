"""A merged file (`hipode merge`, `hipode export --d4rl`) as other libraries' loaders expect it.

The merged file stores every row with its own `next_observations`; synthetic rows are one-step
episodes marked `timeouts` so that nothing joins them to their neighbours. Two common readers
would lose them:
- D4RL's `qlearning_dataset` (CORL) takes s' of row i from observations[i + 1] and drops every
  row whose `timeouts` is set, so it keeps almost no synthetic row;
- d3rlpy's `MDPDataset` cuts episodes at terminals and timeouts and makes T - 1 transitions of
  an episode that timed out, so a one-step synthetic episode gives none.
`qlearning_dataset` and `d3rlpy_arrays` below give each reader what it needs: every synthetic
transition, and the real rows as D4RL's own rule keeps them.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from hipode_pipeline.merge import read_merged


def qlearning_dataset(path: str | Path) -> dict[str, np.ndarray]:
    """D4RL's `qlearning_dataset` dict (observations, actions, next_observations, rewards,
    terminals) plus `is_synthetic`: the real rows as D4RL keeps them (a row at a timeout is
    dropped) with their stored next states, then every synthetic transition."""
    merged = read_merged(Path(path))
    real = merged.real
    keep = ~real.timeouts
    parts = [
        {
            "observations": real.observations[keep],
            "actions": real.actions[keep],
            "next_observations": real.next_observations[keep],
            "rewards": real.rewards[keep],
            "terminals": real.terminals[keep],
            "is_synthetic": np.zeros(int(keep.sum()), dtype=bool),
        }
    ]
    if merged.synthetic is not None:
        synthetic = merged.synthetic
        parts.append(
            {
                "observations": synthetic.observations,
                "actions": synthetic.actions,
                "next_observations": synthetic.next_observations,
                "rewards": synthetic.rewards,
                "terminals": synthetic.terminals,
                "is_synthetic": np.ones(len(synthetic), dtype=bool),
            }
        )
    return {name: np.concatenate([p[name] for p in parts]) for name in parts[0]}


def d3rlpy_arrays(path: str | Path) -> dict[str, np.ndarray]:
    """observations, actions, rewards, terminals and timeouts for d3rlpy's `MDPDataset`:
    the real rows as stored, then each synthetic transition as a two-step episode (s, a, r)
    followed by a landing step at s' that times out, so that d3rlpy's T - 1 rule keeps exactly
    the synthetic transition. A terminal synthetic transition is its own one-step episode
    (terminal episodes keep all T transitions) and its landing step is an episode d3rlpy
    reads as none."""
    merged = read_merged(Path(path))
    real = merged.real
    timeouts = real.timeouts.copy()
    if len(real) and not (real.terminals[-1] or timeouts[-1]):
        timeouts[-1] = True  # the last real episode ends before the synthetic ones
    columns = {
        "observations": [real.observations],
        "actions": [real.actions],
        "rewards": [real.rewards],
        "terminals": [real.terminals],
        "timeouts": [timeouts],
    }
    if merged.synthetic is not None:
        s = merged.synthetic
        m = len(s)
        # row 2i: the transition; row 2i + 1: where it lands (its action and reward unused)
        columns["observations"].append(
            np.stack([s.observations, s.next_observations], axis=1).reshape(2 * m, -1)
        )
        columns["actions"].append(np.repeat(s.actions, 2, axis=0))
        columns["rewards"].append(np.stack([s.rewards, np.zeros_like(s.rewards)], 1).reshape(-1))
        columns["terminals"].append(np.stack([s.terminals, np.zeros(m, dtype=bool)], 1).reshape(-1))
        columns["timeouts"].append(
            np.stack([np.zeros(m, dtype=bool), np.ones(m, dtype=bool)], 1).reshape(-1)
        )
    return {name: np.concatenate(parts) for name, parts in columns.items()}
