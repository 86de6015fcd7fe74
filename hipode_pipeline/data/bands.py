"""Behaviour-score bands: whether a collected dataset's behaviour policy scored where the policy
of that kind scored in D4RL (stages/collect.toml `medium_band`, from D4RL's medium data),
recorded in the dataset's metadata when it is collected and checked before any stage uses it.

A dataset whose policy missed its band is another dataset than its name says (a "medium-replay"
of a policy far below medium), so every figure on it would mislead: collection ends with a
non-zero exit, and `augment` and `train` refuse such a source unless told otherwise, and then
record that they were.
"""

from __future__ import annotations

import tomllib
from typing import Any

from hipode_pipeline.errors import HipodeError
from hipode_pipeline.paths import stages_dir

# which behaviour policies a dataset kind is made of, each checked against its band
POLICIES_OF_KIND = {
    "random": (),
    "medium": ("medium",),
    "medium-replay": ("medium",),
    "medium-expert": ("medium", "expert"),
    "expert": ("expert",),
}
ALLOW_FLAG = "--allow-off-band"


class OffBandError(HipodeError):
    """A dataset whose behaviour policy scored outside the band of its kind."""

    exit_code = 3


def band_record(
    kind: str, bands: dict[str, tuple[float, float] | None], behaviour: dict[str, Any]
) -> dict[str, Any]:
    """The dataset's band verdict: per behaviour policy its band, measured normalized score and
    whether it lies inside; `in_band` is False if any policy missed, None where no band is
    recorded (random data, kinds without one), else True."""
    policies = {}
    for name in POLICIES_OF_KIND.get(kind, ()):
        band = bands.get(name)
        measured = (behaviour.get(name) or {}).get("normalized")
        inside = None
        if band is not None and isinstance(measured, int | float):
            inside = bool(band[0] <= measured <= band[1])
        policies[name] = {
            "band": None if band is None else [float(band[0]), float(band[1])],
            "measured": measured,
            "in_band": inside,
        }
    verdicts = [policy["in_band"] for policy in policies.values()]
    if False in verdicts:
        in_band = False
    elif verdicts and None not in verdicts:
        in_band = True
    else:
        in_band = None
    return {"kind": kind, "policies": policies, "in_band": in_band}


def dataset_band(metadata: dict[str, Any]) -> dict[str, Any] | None:
    """The band verdict of a dataset collected here, from its metadata (recomputed from its
    recipe and behaviour scores when it was collected before bands were recorded); None for
    data from elsewhere, which records no behaviour policy."""
    hipode = metadata.get("hipode") if isinstance(metadata, dict) else None
    if not isinstance(hipode, dict):
        return None
    if isinstance(hipode.get("band"), dict):
        return hipode["band"]
    recipe, behaviour = hipode.get("recipe"), hipode.get("behaviour_policy")
    if not isinstance(recipe, dict) or not isinstance(behaviour, dict):
        return None
    medium = recipe.get("medium_band", "absent")
    if medium == "absent" and recipe.get("profile") == "full" and recipe.get("env"):
        # collected before bands were recorded: the env's band as the registry has it now
        medium = registry_medium_band(str(recipe["env"]))
    bands = {"medium": tuple(medium) if isinstance(medium, list | tuple) and medium else None}
    return band_record(str(hipode.get("kind")), bands, behaviour)


def registry_medium_band(env: str) -> list[float] | None:
    """stages/collect.toml's medium_band for `env` ([env] over [defaults]); None if unset."""
    with open(stages_dir() / "collect.toml", "rb") as f:
        recipes = tomllib.load(f)
    band = recipes.get(env, {}).get("medium_band", recipes.get("defaults", {}).get("medium_band"))
    return list(band) if isinstance(band, list) and len(band) == 2 else None


def off_band_text(record: dict[str, Any]) -> str:
    """What missed: 'medium scored 15.7 normalized, outside its band [38, 46]'."""
    missed = [
        f"{name} scored {policy['measured']:.1f} normalized, outside its band "
        f"[{policy['band'][0]:g}, {policy['band'][1]:g}]"
        for name, policy in record["policies"].items()
        if policy["in_band"] is False
    ]
    return "; ".join(missed)


def check_source_band(
    metadata: dict[str, Any], origin: str, *, allow_off_band: bool
) -> dict[str, Any] | None:
    """Refuse a source whose behaviour policy missed its band unless `allow_off_band`; return
    the band verdict to record (None for data that records no behaviour policy)."""
    record = dataset_band(metadata)
    if record is not None and record["in_band"] is False and not allow_off_band:
        raise OffBandError(
            f"{origin}: the behaviour policy of this {record['kind']} dataset "
            f"{off_band_text(record)} (D4RL's policy of that kind scores inside it), so the "
            f"data is not what its name says. Collect it again with a larger training budget "
            f"(stages/collect.toml), or pass {ALLOW_FLAG} to use it anyway; the output then "
            "records that it was built on an off-band source"
        )
    return record
