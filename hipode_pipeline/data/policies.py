"""Behaviour-policy files of `hipode collect`: a frozen numpy policy of either trainer (PPO's
Gaussian, SAC's tanh-Gaussian) and what training recorded about it."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from hipode_pipeline.data.ppo import GaussianPolicy, load_checkpoint
from hipode_pipeline.data.sac import TanhGaussianPolicy
from hipode_pipeline.errors import DataFormatError
from hipode_pipeline.files import save_torch_atomic

BehaviourPolicy = GaussianPolicy | TanhGaussianPolicy
# the policy classes by the name their state records; PPO's files predate the name
POLICY_CLASSES = {"gaussian": GaussianPolicy, "tanh_gaussian": TanhGaussianPolicy}


def save_policy(policy: BehaviourPolicy, path: Path, info: dict[str, Any]) -> None:
    save_torch_atomic(path, {"policy": policy.state_dict(), "info": json.dumps(info)})


def load_policy(path: Path) -> tuple[BehaviourPolicy, dict[str, Any]]:
    state = load_checkpoint(path)
    name = state["policy"].get("class", "gaussian")
    if name not in POLICY_CLASSES:
        raise DataFormatError(path, "policy.class", f"one of {sorted(POLICY_CLASSES)}", name)
    return POLICY_CLASSES[name].from_state_dict(state["policy"]), json.loads(state["info"])
