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

import functools
import hashlib

import numpy as np
from numpy.random.bit_generator import ISeedSequence

#: Layers (and purposes) that draw random numbers. A closed set, so a typo
#: fails loudly instead of silently opening a new, unrelated stream.
LAYERS = ("scenario", "entity", "information", "system", "jitter")


@functools.lru_cache(maxsize=64)
def _words(text: str) -> tuple[int, ...]:
    """Stable 32-bit words from a string (Python's hash() is salted per process)."""
    digest = hashlib.blake2b(text.encode("utf-8"), digest_size=16).digest()
    return tuple(int.from_bytes(digest[i:i + 4], "little") for i in range(0, 16, 4))


def _entropy(seed: int, twin: str, step: int, layer: str) -> list[int]:
    if layer not in LAYERS:
        raise ValueError(f"unknown stream layer {layer!r}; expected one of {', '.join(LAYERS)}")
    if int(seed) < 0:
        raise ValueError(f"seed must be non-negative, got {seed!r}")
    if int(step) < 0:
        raise ValueError(f"step must be non-negative, got {step!r}")
    return [int(seed) & 0xFFFFFFFF, int(seed) >> 32, *_words(twin), int(step), LAYERS.index(layer)]


def seed_sequence(seed: int, twin: str, step: int, layer: str) -> np.random.SeedSequence:
    """The SeedSequence of one (seed, twin, step, layer)."""
    return np.random.SeedSequence(_entropy(seed, twin, step, layer))


def _uint32_words(values: list[int]) -> np.ndarray:
    """The entropy as numpy's SeedSequence reads a list of non-negative ints: 32-bit words, little end first."""
    words = []
    for value in values:
        words.append(value & 0xFFFFFFFF)
        value >>= 32
        while value:
            words.append(value & 0xFFFFFFFF)
            value >>= 32
    return np.array(words, dtype=np.int64)


class _PCG64Seed(ISeedSequence):
    """The 4 uint64 words SeedSequence(entropy, spawn_key) hands a PCG64, computed by :mod:`dtpf.messages._seedseq`."""

    __slots__ = ("state",)

    def __init__(self, entropy: list[int], spawn_key: tuple[int, ...] = ()):
        from dtpf.messages import _seedseq  # numba on first use: processes that draw nothing skip it

        # numpy assembles the entropy's words, then the spawn key's (the entropy has more than 4 words:
        # no padding between them).
        words = _uint32_words(entropy)
        if spawn_key:
            words = np.concatenate((words, _uint32_words(list(spawn_key))))
        self.state = _seedseq.state_words(words).view(np.uint64)

    def generate_state(self, n_words, dtype=np.uint32):
        if n_words != 4 or np.dtype(dtype) != np.uint64:
            raise ValueError("a PCG64 seed gives 4 uint64 words only")
        return self.state


def stream(seed: int, twin: str, step: int, layer: str) -> np.random.Generator:
    """A fresh Generator (PCG64) for one (seed, twin, step, layer): the generator
    ``Generator(PCG64(seed_sequence(seed, twin, step, layer)))``, the same numbers, built several times faster."""
    return np.random.Generator(np.random.PCG64(_PCG64Seed(_entropy(seed, twin, step, layer))))


def block_stream(seed: int, twin: str, step: int, layer: str, block: int) -> np.random.Generator:
    """The stream of block ``block`` >= 1 of a set worked on in blocks (:mod:`dtpf.entity.cores`):
    ``Generator(PCG64(SeedSequence(entropy, spawn_key=(block,))))`` with the entropy of
    ``stream(seed, twin, step, layer)``, the child ``block`` of the step's stream; block 0 draws from the
    step's stream itself."""
    if int(block) < 1:
        raise ValueError(f"a block's own stream is for blocks 1, 2, ...; got {block!r}")
    return np.random.Generator(np.random.PCG64(_PCG64Seed(_entropy(seed, twin, step, layer), (int(block),))))
