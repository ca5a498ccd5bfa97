"""Random streams derived per (seed, twin, step, layer).

Every random number a layer draws at a filter step comes from
``stream(seed, twin, step, layer)``. Because the stream depends only on these
four values, the three layers running as separate processes over Zenoh draw
exactly the numbers the same run draws in one process, whatever the order in
which messages arrive.

Example::

    rng = stream(seed=7, twin="ungm-1", step=12, layer="information")
    u = rng.random(1000)
"""
from __future__ import annotations

import hashlib

import numpy as np

#: Layers (and purposes) that draw random numbers. A closed set, so a typo
#: fails loudly instead of silently opening a new, unrelated stream.
LAYERS = ("scenario", "entity", "information", "system")


def _words(text: str) -> list[int]:
    """Stable 32-bit words from a string (Python's hash() is salted per process)."""
    digest = hashlib.blake2b(text.encode("utf-8"), digest_size=16).digest()
    return [int.from_bytes(digest[i:i + 4], "little") for i in range(0, 16, 4)]


def seed_sequence(seed: int, twin: str, step: int, layer: str) -> np.random.SeedSequence:
    """The SeedSequence of one (seed, twin, step, layer)."""
    if layer not in LAYERS:
        raise ValueError(f"unknown stream layer {layer!r}; expected one of {', '.join(LAYERS)}")
    if int(seed) < 0:
        raise ValueError(f"seed must be non-negative, got {seed!r}")
    if int(step) < 0:
        raise ValueError(f"step must be non-negative, got {step!r}")
    entropy = [int(seed) & 0xFFFFFFFF, int(seed) >> 32, *_words(twin), int(step), LAYERS.index(layer)]
    return np.random.SeedSequence(entropy)


def stream(seed: int, twin: str, step: int, layer: str) -> np.random.Generator:
    """A fresh Generator (PCG64) for one (seed, twin, step, layer)."""
    return np.random.Generator(np.random.PCG64(seed_sequence(seed, twin, step, layer)))
