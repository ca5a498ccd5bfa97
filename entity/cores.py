"""The threads a process computes on, and the blocks its kernels share among them.

A set of N particles is worked on in blocks of B (a run's ``block_particles``,
:data:`dtpf.messages.config.BLOCK_PARTICLES` for a new run): threads take
blocks, a sum adds the blocks' partial sums in block order, and block b draws
its random numbers from a stream that depends on the step's stream and b only
(block 0 from the step's stream itself). So the numbers do not depend on the
thread count, and for N <= B (one block) they are those of one thread without
blocks. Kernels whose numbers do not depend on how the set is cut (an
element-wise pass, a histogram of integers, a copy) share any large set among
the threads.

The thread count is a setting of the process, never of the run::

    from dtpf.entity import cores
    cores.set_threads(2)        # None: every core this process may use
    cores.blocks(1_000_000, 65_536)   # 16
"""
from __future__ import annotations

import os

# Threads that wait for the next parallel region sleep instead of spinning: the layers of a twin share the
# machine's cores with each other (and with other work), and a thread spinning in one process takes the
# core another needs. On 2 cores with one busy, OpenMP's default spin made a radix select 10x slower, and
# an empty parallel loop took 9 us passive, 57 us after 1,000 spins (GOMP_SPINCOUNT), 1 ms after 20,000.
# Read when numba first starts its threads, after this import; a value the environment gives is kept.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import numba  # noqa: E402 - after the wait policy

from dtpf.messages import arrays  # noqa: E402

__all__ = ["available", "set_threads", "threads", "use", "blocks", "parallel", "parts", "in_parts", "PARALLEL_MIN",
           "CHUNK"]

#: From this many particles on, a kernel shares the set among the threads; below it one thread is faster:
#: waking a sleeping thread costs 10-60 us on a 2-core VM (dtpf.scripts.bench.cores), and a kernel at
#: N = 1e5 takes 0.05-0.5 ms. A set in blocks of fewer particles runs its blocks on one thread: the same
#: numbers.
PARALLEL_MIN = 1 << 18

#: Elements of one chunk of an element-wise parallel loop: threads take chunks (and blocks) one at a time, so
#: that a thread slowed by another process's work takes fewer of them.
CHUNK = 1 << 13

#: The process's thread count (None: not set, every core it may use).
_THREADS: int | None = None


def available() -> int:
    """The cores this process may run on (its CPU affinity), at most numba's thread pool."""
    try:
        cores = len(os.sched_getaffinity(0))
    except AttributeError:  # no affinity on this platform
        cores = os.cpu_count() or 1
    return max(1, min(cores, numba.config.NUMBA_NUM_THREADS))


def set_threads(count: int | None = None) -> int:
    """Compute on ``count`` threads (None: :func:`available`), clipped to numba's pool; the count set."""
    global _THREADS
    if count is not None and int(count) < 1:
        raise ValueError(f"threads must be at least 1, got {count!r}")
    _THREADS = available() if count is None else max(1, min(int(count), numba.config.NUMBA_NUM_THREADS))
    numba.set_num_threads(_THREADS)
    arrays.set_check_threads(_THREADS)
    return _THREADS


def threads() -> int:
    """The process's thread count."""
    return available() if _THREADS is None else _THREADS


def use(n: int | None = None) -> int:
    """Apply the thread count for a kernel over ``n`` particles on the calling thread (numba's settings are
    per thread): the process's, or 1 below PARALLEL_MIN; threads take the iterations of a parallel loop
    (blocks, parts or chunks) one at a time. The count."""
    count = threads() if n is None or n >= PARALLEL_MIN else 1
    if numba.get_num_threads() != count:
        numba.set_num_threads(count)
    numba.set_parallel_chunksize(1)
    return count


def parts(n: int, most: int | None = None) -> int:
    """Parts of PARALLEL_MIN particles that a set of ``n`` is cut into for a kernel whose numbers do not depend
    on the cut (at least one a thread, at most ``most``)."""
    count = max(threads(), -(-int(n) // PARALLEL_MIN))
    return count if most is None else max(1, min(count, int(most)))


def blocks(n: int, block: int | None) -> int:
    """The blocks of B = ``block`` particles that N = ``n`` needs: 1 for N <= B or no B (a log recorded
    before blocks), else ceil(N / B)."""
    if block is None or n <= block:
        return 1
    return -(-int(n) // int(block))


def parallel(n: int) -> bool:
    """Whether a kernel whose numbers do not depend on the cut shares ``n`` particles among threads."""
    return use(n) > 1


def in_parts(n: int, work, parts: int | None = None) -> None:
    """``work(start, end)`` over ``parts`` (default: the process's threads, 1 below PARALLEL_MIN) contiguous
    parts of [0, n): the first on the calling thread, the others on a pool of Python threads, for work that
    releases the GIL (numpy's element-wise ufuncs, nogil kernels). Only for work whose result does not depend
    on the cut."""
    if parts is None:
        parts = threads() if n >= PARALLEL_MIN else 1
    count = max(1, min(int(parts), n))
    if count == 1:
        work(0, n)
        return
    bounds = [n * p // count for p in range(count + 1)]
    pool = _pool(count)
    futures = [pool.submit(work, bounds[p], bounds[p + 1]) for p in range(1, count)]
    try:
        work(bounds[0], bounds[1])
    finally:
        for future in futures:
            future.result()


_POOLS: dict[int, object] = {}


def _pool(count: int):
    """A pool of ``count`` - 1 Python threads (the caller is the other), made once per count."""
    from concurrent.futures import ThreadPoolExecutor

    pool = _POOLS.get(count)
    if pool is None:
        pool = _POOLS[count] = ThreadPoolExecutor(max_workers=count - 1, thread_name_prefix="dtpf-parts")
    return pool
