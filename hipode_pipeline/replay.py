"""Real and synthetic transitions in one preallocated tensor on the device, sampled as η-mixed
batches (METHOD.md, appendix B.4: round(η·B) synthetic and B − round(η·B) real rows per batch)
or uniformly over the union, for K training seeds at once: each seed draws its rows from its
own random stream, and one gather serves them all."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Literal, NamedTuple

import numpy as np
import torch

from hipode_pipeline.data.transitions import Transitions
from hipode_pipeline.errors import HipodeError


class Batch(NamedTuple):
    """One minibatch of raw (un-normalized) transitions on the learner's device, one per seed:
    (K, B, ...) from the replay; a one-seed learner also takes a plain (B, ...) batch."""

    observations: torch.Tensor  # (K, B, ds)
    actions: torch.Tensor  # (K, B, da)
    rewards: torch.Tensor  # (K, B)
    next_observations: torch.Tensor  # (K, B, ds)
    dones: torch.Tensor  # (K, B) 1.0 where the MDP ended (terminal, not timeout)


Mixing = Literal["mixed", "union"]
MIXING_MODES = ("mixed", "union")


def _pack(t: Transitions) -> np.ndarray:
    """(N, 2·ds + da + 2) float32 rows: s, a, r, s', done (terminal only: timeouts bootstrap)."""
    return np.concatenate(
        [
            t.observations,
            t.actions,
            t.rewards[:, None],
            t.next_observations,
            t.terminals[:, None].astype(np.float32),
        ],
        axis=1,
        dtype=np.float32,
    )


def uses_synthetic(eta: float, mixing: Mixing, n_synthetic: int) -> bool:
    """Whether batches draw synthetic rows: some exist, and "union" or eta > 0 asks for them."""
    return n_synthetic > 0 and (mixing == "union" or eta > 0)


def synthetic_batch_count(eta: float, mixing: Mixing, n_synthetic: int, batch: int) -> int:
    """Synthetic rows in every batch of `batch` rows under "mixed" (random under "union": 0)."""
    return round(eta * batch) if mixing == "mixed" and n_synthetic else 0


def synthetic_batch_share(
    eta: float, mixing: Mixing, n_real: int, n_synthetic: int, batch: int
) -> float:
    """The share of synthetic rows in a batch: exactly round(eta·B)/B under "mixed", their
    share of the union in expectation under "union"."""
    if not uses_synthetic(eta, mixing, n_synthetic):
        return 0.0
    if mixing == "union":
        return n_synthetic / (n_real + n_synthetic)
    return synthetic_batch_count(eta, mixing, n_synthetic, batch) / batch


class MixedReplay:
    """Sampler over real (source) and synthetic transitions.

    Rows 0..n_real-1 of the packed tensor are real, the rest synthetic. With mixing "mixed"
    each batch holds exactly round(eta·B) synthetic rows (the first ones of the batch are real);
    with "union" rows are drawn uniformly over both. eta = 0 (or no synthetic data) never
    copies or reads a synthetic row. `seed` is one training seed or a list of them: batches
    then come as (K, B, ...), seed k's rows drawn from a generator seeded with seed k alone.
    """

    def __init__(
        self,
        real: Transitions,
        synthetic: Transitions | None = None,
        *,
        eta: float = 0.0,
        mixing: Mixing = "mixed",
        device: torch.device | str = "cpu",
        seed: int | Sequence[int] = 0,
    ):
        if mixing not in MIXING_MODES:
            raise HipodeError(f"mixing: expected one of {MIXING_MODES}, found {mixing!r}")
        if not 0.0 <= eta <= 1.0:
            raise HipodeError(f"eta (synthetic rate): expected a number in [0, 1], found {eta}")
        use_synthetic = synthetic is not None and uses_synthetic(eta, mixing, len(synthetic))
        if mixing == "mixed" and eta > 0 and not use_synthetic:
            raise HipodeError(
                f"eta = {eta} asks for synthetic rows but no synthetic transitions were given"
            )
        if use_synthetic and (synthetic.obs_dim, synthetic.act_dim) != (real.obs_dim, real.act_dim):
            raise HipodeError(
                "synthetic transitions: expected obs/act dims "
                f"{(real.obs_dim, real.act_dim)} like the source, "
                f"found {(synthetic.obs_dim, synthetic.act_dim)}"
            )
        self.eta, self.mixing = float(eta), mixing
        self.obs_dim, self.act_dim = real.obs_dim, real.act_dim
        self.n_real = len(real)
        self.n_synthetic = len(synthetic) if use_synthetic else 0
        self.device = torch.device(device)
        parts = [_pack(real)] + ([_pack(synthetic)] if use_synthetic else [])
        self.data = torch.from_numpy(np.concatenate(parts) if len(parts) > 1 else parts[0]).to(
            self.device
        )
        ds, da = self.obs_dim, self.act_dim
        # column boundaries of s | a | r | s' | done in a packed row
        self._splits = [ds, da, 1, ds, 1]
        seeds = [seed] if isinstance(seed, int) else list(seed)
        self.generators = [torch.Generator(device=self.device).manual_seed(s) for s in seeds]

    def __len__(self) -> int:
        return self.n_real + self.n_synthetic

    def synthetic_count(self, batch_size: int) -> int:
        """Synthetic rows in every batch of this size under "mixed" (random under "union")."""
        return synthetic_batch_count(self.eta, self.mixing, self.n_synthetic, batch_size)

    def _indices(self, g: torch.Generator, batch_size: int) -> torch.Tensor:
        dev = self.device
        if self.mixing == "union":
            return torch.randint(len(self), (batch_size,), generator=g, device=dev)
        n_syn = self.synthetic_count(batch_size)
        if n_syn == 0:
            return torch.randint(self.n_real, (batch_size,), generator=g, device=dev)
        real = torch.randint(self.n_real, (batch_size - n_syn,), generator=g, device=dev)
        syn = torch.randint(self.n_synthetic, (n_syn,), generator=g, device=dev) + self.n_real
        return torch.cat([real, syn])

    def sample_indices(self, batch_size: int) -> torch.Tensor:
        """(K, B) row indices into the packed tensor; per seed real rows first, then synthetic."""
        return torch.stack([self._indices(g, batch_size) for g in self.generators])

    def sample(self, batch_size: int) -> Batch:
        indices = self.sample_indices(batch_size)
        rows = self.data.index_select(0, indices.flatten()).view(*indices.shape, -1)
        obs, actions, rewards, next_obs, dones = rows.split(self._splits, dim=-1)
        return Batch(obs, actions, rewards.squeeze(-1), next_obs, dones.squeeze(-1))

    def seed_state(self, k: int = 0) -> dict:
        """Seed index k's sampling state, as a one-seed replay saves it."""
        return {"generator": self.generators[k].get_state()}

    def load_seed_states(self, states: list[dict]) -> None:
        if len(states) != len(self.generators):
            raise HipodeError(
                f"replay state: expected {len(self.generators)} seed states, found {len(states)}"
            )
        for generator, state in zip(self.generators, states, strict=True):
            generator.set_state(state["generator"])

    def state_dict(self) -> dict:
        """A one-seed replay's state (seed_state(0))."""
        if len(self.generators) != 1:
            raise HipodeError(f"state_dict: {len(self.generators)} seeds; use seed_state(k)")
        return self.seed_state(0)

    def load_state_dict(self, state: dict) -> None:
        self.load_seed_states([state])
