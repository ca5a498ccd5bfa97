"""SeedSequence's state, compiled (for :func:`dtpf.messages.streams.stream`).

numpy builds ``SeedSequence(entropy).generate_state(4, uint64)``, the 256 bits
that seed a PCG64, in Python loops over uint32 scalars: most of what making a
stream costs, once per layer and step. These are the same hash and mix
functions (numpy/random/bit_generator.pyx, after O'Neill's seed_seq), compiled.
"""
from __future__ import annotations

import numba
import numpy as np

_INIT_A, _MULT_A, _INIT_B, _MULT_B = 0x43B0D7E5, 0x931E8875, 0x8B51F9DD, 0x58F38DED
_MIX_MULT_L, _MIX_MULT_R, _MASK32, _POOL = 0xCA01F9DD, 0x4973F715, 0xFFFFFFFF, 4


@numba.njit(inline="always")
def _hashmix(value, hash_const):  # pragma: no cover - compiled
    value = (value ^ hash_const) & _MASK32
    hash_const = (hash_const * _MULT_A) & _MASK32
    value = (value * hash_const) & _MASK32
    return value ^ (value >> 16), hash_const


@numba.njit(inline="always")
def _mix(x, y):  # pragma: no cover - compiled
    result = (_MIX_MULT_L * x - _MIX_MULT_R * y) & _MASK32
    return result ^ (result >> 16)


@numba.njit(cache=True, nogil=True)
def state_words(entropy):  # pragma: no cover - compiled
    # SeedSequence(entropy).generate_state(8, uint32) for uint32 words ``entropy`` (int64 array).
    pool = np.zeros(_POOL, dtype=np.int64)
    hash_const = _INIT_A
    for i in range(_POOL):
        pool[i], hash_const = _hashmix(entropy[i] if i < entropy.shape[0] else 0, hash_const)
    for i_src in range(_POOL):
        for i_dst in range(_POOL):
            if i_src != i_dst:
                value, hash_const = _hashmix(pool[i_src], hash_const)
                pool[i_dst] = _mix(pool[i_dst], value)
    for i_src in range(_POOL, entropy.shape[0]):
        for i_dst in range(_POOL):
            value, hash_const = _hashmix(entropy[i_src], hash_const)
            pool[i_dst] = _mix(pool[i_dst], value)
    state = np.empty(8, dtype=np.uint32)
    hash_const = _INIT_B
    for i in range(8):
        value = (pool[i % _POOL] ^ hash_const) & _MASK32
        hash_const = (hash_const * _MULT_B) & _MASK32
        value = (value * hash_const) & _MASK32
        state[i] = value ^ (value >> 16)
    return state
