"""Seeded damaged copies of a real file for mutation fuzzing (tests/test_hostile_corpus.py); the crafted
scenes an attacker would upload are service.hostile_corpus."""
from __future__ import annotations

import random


def mutations(data: bytes, n: int, seed: int = 0) -> list[bytes]:
    """`n` damaged copies of `data`: truncations at random lengths, runs of flipped bytes, and zeroed
    blocks, in a seeded order (the same corpus every run)."""
    rng = random.Random(seed)
    out = []
    for k in range(n):
        kind = k % 3
        if kind == 0 or len(data) < 16:
            out.append(data[: rng.randrange(1, max(2, len(data)))])
            continue
        b = bytearray(data)
        if kind == 1:
            for _ in range(rng.randint(1, 16)):
                i = rng.randrange(len(b))
                b[i] ^= 1 << rng.randrange(8)
        else:
            i = rng.randrange(len(b))
            j = min(len(b), i + rng.randint(1, 256))
            b[i:j] = bytes(j - i) if rng.random() < 0.5 else bytes(rng.randrange(256) for _ in range(j - i))
        out.append(bytes(b))
    return out
