"""Seeds of named random streams: one formula for every stream of every stage."""

from __future__ import annotations

import hashlib

SEED_MAX = 2**63 - 1  # torch.Generator.manual_seed and numpy accept 63-bit seeds everywhere


def derive_seed(seed: int, stream: str) -> int:
    """An independent 63-bit seed for the stream `stream` of a run seeded with `seed`."""
    digest = hashlib.sha256(f"{seed}:{stream}".encode()).digest()
    return int.from_bytes(digest[:8], "little") % (2**63)
