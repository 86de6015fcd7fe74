"""Networks of K independent learners (one per training seed) as one set of batched matmuls.

Every parameter carries the seed as its leading dimension, so one Adam step, one Polyak lerp
and one bmm per layer serve all seeds, while no number of one seed ever mixes with another's:
the loss is the sum of the seeds' own losses, whose gradients are each seed's own. Each seed's
initial weights come from a generator seeded with that seed alone, so seed k starts the same in
a run of one seed or of many.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from torch import nn


def init_generators(seeds: Sequence[int]) -> list[torch.Generator]:
    """One CPU generator per seed for weight initialization (device independent)."""
    return [torch.Generator().manual_seed(int(seed)) for seed in seeds]


def _uniform(shape: tuple[int, ...], bound: float, generator: torch.Generator) -> torch.Tensor:
    return torch.empty(shape).uniform_(-bound, bound, generator=generator)


def linear_init(
    generators: Sequence[torch.Generator], fan_in: int, fan_out: int, members: int | None = None
) -> tuple[torch.Tensor, torch.Tensor]:
    """nn.Linear's default init, per seed (and per member): U(±1/sqrt(fan_in)) for both.

    Shapes (K, fan_in, fan_out) and (K, 1, fan_out), or with a member axis after K."""
    bound = 1.0 / math.sqrt(fan_in)
    lead = () if members is None else (members,)
    weights, biases = [], []
    for g in generators:
        weights.append(_uniform((*lead, fan_in, fan_out), bound, g))
        biases.append(_uniform((*lead, 1, fan_out), bound, g))
    return torch.stack(weights), torch.stack(biases)


def matmul_dtype(use_bf16: bool) -> torch.dtype:
    return torch.bfloat16 if use_bf16 else torch.float32


def run_layers(h: torch.Tensor, layers, use_bf16: bool) -> torch.Tensor:
    """h (G, N, in) through (w (G, in, out), b (G, 1, out)) layers with ReLU between them; the
    hidden layers in bf16 when asked (a no-op cast in fp32), the last one always in fp32."""
    last = len(layers) - 1
    hidden = matmul_dtype(use_bf16)
    for i, (w, b) in enumerate(layers):
        dtype = torch.float32 if i == last else hidden
        h = torch.baddbmm(b.to(dtype), h.to(dtype), w.to(dtype))
        if i < last:
            h = torch.relu_(h)  # in place: the fresh output it would write costs more
    return h


class StackedMLP(nn.Module):
    """K MLPs with ReLU between layers: (K, ..., in) -> (K, ..., out).

    Hidden layers run in `hidden_dtype` when bf16 is asked for; the output layer always runs
    in fp32, so heads (Q-values, actions, log-stds) and everything computed from them are fp32.
    """

    def __init__(
        self,
        dims: Sequence[int],
        generators: Sequence[torch.Generator],
        output_activation: nn.Module | None = None,
    ):
        super().__init__()
        self.weights = nn.ParameterList()
        self.biases = nn.ParameterList()
        for fan_in, fan_out in zip(dims[:-1], dims[1:], strict=True):
            w, b = linear_init(generators, fan_in, fan_out)
            self.weights.append(nn.Parameter(w))
            self.biases.append(nn.Parameter(b))
        self.output_activation = output_activation
        self.use_bf16 = False

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        k, lead = x.shape[0], x.shape[1:-1]
        layers = list(zip(self.weights, self.biases, strict=True))
        h = run_layers(x.reshape(k, -1, x.shape[-1]), layers, self.use_bf16)
        if self.output_activation is not None:
            h = self.output_activation(h)
        return h.reshape(k, *lead, h.shape[-1])


class StackedTwinCritic(nn.Module):
    """K seeds × M Q-networks Q(s, a): parameters (K, M, in, out), one bmm over K·M per layer.

    Inputs are per seed, (K, ..., ds) and (K, ..., da), shared by that seed's M critics; the
    output is (K, M, ...), the output layer in fp32 like StackedMLP's."""

    def __init__(
        self,
        obs_dim: int,
        act_dim: int,
        generators: Sequence[torch.Generator],
        hidden_dim: int = 256,
        n_hidden: int = 2,
        members: int = 2,
    ):
        super().__init__()
        dims = [obs_dim + act_dim, *([hidden_dim] * n_hidden), 1]
        self.weights = nn.ParameterList()
        self.biases = nn.ParameterList()
        for fan_in, fan_out in zip(dims[:-1], dims[1:], strict=True):
            w, b = linear_init(generators, fan_in, fan_out, members)
            self.weights.append(nn.Parameter(w))
            self.biases.append(nn.Parameter(b))
        self.use_bf16 = False

    def forward(self, observations: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
        x = torch.cat([observations, actions], dim=-1)
        k, lead = x.shape[0], x.shape[1:-1]
        m = self.weights[0].shape[1]
        h = x.reshape(k, 1, -1, x.shape[-1]).expand(-1, m, -1, -1).reshape(k * m, -1, x.shape[-1])
        layers = [
            (w.reshape(k * m, *w.shape[2:]), b.reshape(k * m, *b.shape[2:]))
            for w, b in zip(self.weights, self.biases, strict=True)
        ]
        return run_layers(h, layers, self.use_bf16).reshape(k, m, *lead)

    def first(
        self, observations: torch.Tensor, actions: torch.Tensor, *, frozen: bool = False
    ) -> torch.Tensor:
        """Each seed's Q1 alone, (K, ...); `frozen` detaches the weights so only the inputs get
        gradients (the actor step)."""
        x = torch.cat([observations, actions], dim=-1)
        k, lead = x.shape[0], x.shape[1:-1]
        layers = [
            (w[:, 0].detach(), b[:, 0].detach()) if frozen else (w[:, 0], b[:, 0])
            for w, b in zip(self.weights, self.biases, strict=True)
        ]
        h = run_layers(x.reshape(k, -1, x.shape[-1]), layers, self.use_bf16)
        return h.reshape(k, *lead)


def orthogonal_(weight: torch.Tensor, gain: float, generators: Sequence[torch.Generator]) -> None:
    """Orthogonal init of every (in, out) matrix of a (K, ..., in, out) weight, seed k's from
    generator k."""
    with torch.no_grad():
        for seed_weight, g in zip(weight, generators, strict=True):
            for matrix in seed_weight.view(-1, *weight.shape[-2:]):
                nn.init.orthogonal_(matrix, gain=gain, generator=g)


def xavier_uniform_(
    weight: torch.Tensor, gain: float, generators: Sequence[torch.Generator]
) -> None:
    """Xavier-uniform init of each seed's (in, out) matrix from that seed's generator."""
    with torch.no_grad():
        for matrix, g in zip(weight, generators, strict=True):
            nn.init.xavier_uniform_(matrix, gain=gain, generator=g)
