"""Offline learners for stage two: TD3+BC, IQL and CQL (one file each), by name."""

from __future__ import annotations

from hipode_pipeline.errors import HipodeError
from hipode_pipeline.learners.base import Batch, Learner, LearnerConfig
from hipode_pipeline.learners.cql import CQL, CQLConfig
from hipode_pipeline.learners.iql import IQL, IQLConfig
from hipode_pipeline.learners.td3_bc import TD3BC, TD3BCConfig

LEARNERS: dict[str, type[Learner]] = {"td3bc": TD3BC, "iql": IQL, "cql": CQL}

__all__ = [
    "Batch",
    "CQL",
    "CQLConfig",
    "IQL",
    "IQLConfig",
    "LEARNERS",
    "Learner",
    "LearnerConfig",
    "TD3BC",
    "TD3BCConfig",
    "learner_class",
]


def learner_class(name: str) -> type[Learner]:
    """The built-in learner called `name` (td3bc | iql | cql)."""
    if name not in LEARNERS:
        raise HipodeError(
            f"learner '{name}': expected one of {sorted(LEARNERS)} or 'd3rlpy:<AlgoName>'"
        )
    return LEARNERS[name]
