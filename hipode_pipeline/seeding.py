"""Seeds of named random streams: one formula for every stream of every stage."""

from __future__ import annotations

import hashlib
import re

from hipode_pipeline.errors import SettingError

SEED_MAX = 2**63 - 1  # torch.Generator.manual_seed and numpy accept 63-bit seeds everywhere


def derive_seed(seed: int, stream: str) -> int:
    """An independent 63-bit seed for the stream `stream` of a run seeded with `seed`."""
    digest = hashlib.sha256(f"{seed}:{stream}".encode()).digest()
    return int.from_bytes(digest[:8], "little") % (2**63)


MAX_SEEDS_LISTED = 10_000  # seeds one list may name (a typo like 0-99999999 is refused early)
SEED_ITEM = re.compile(r"([0-9]+)(?:-([0-9]+))?")


def parse_seeds(text: str, flag: str = "--seeds") -> list[int]:
    """Seeds written as ranges and lists, "0-4" or "0,2,5" or "0-2,7", in the order given."""
    seeds: list[int] = []
    for item in (part.strip() for part in str(text).split(",")):
        match = SEED_ITEM.fullmatch(item)
        if match is None:
            raise SettingError(
                f"{flag}: expected seeds like 0-4 or 0,2,5 (integers >= 0), found {text!r}"
            )
        first = int(match.group(1))
        last = int(match.group(2)) if match.group(2) is not None else first
        if not first <= last <= SEED_MAX:
            raise SettingError(
                f"{flag}: expected ranges low-high with 0 <= low <= high <= {SEED_MAX}, "
                f"found {item!r}"
            )
        if len(seeds) + last - first + 1 > MAX_SEEDS_LISTED:
            raise SettingError(f"{flag}: expected at most {MAX_SEEDS_LISTED} seeds, found more")
        seeds.extend(range(first, last + 1))
    if len(set(seeds)) != len(seeds):
        raise SettingError(f"{flag}: expected each seed once, found {text!r}")
    return seeds
