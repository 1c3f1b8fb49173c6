"""How the compiled smoothers split a long recording over two threads, and the threads.

The cost of a trial point (`smoothers._compiled_cost.cost`, a third of an iteration) needs no
recursion over the samples: on a recording of `SPLIT_MIN_SAMPLES` or more it runs as two ranges
of samples on two threads (`smoothers._compiled_cost.range_cost`; the kernels release the GIL),
each writing its own rows, and their sums are added in a fixed order. The split depends on the
number of samples alone, so every result is the same on any machine; it changes the wall time,
not the CPU time. The linearisation's elimination is a recursion; on a long recording
(`linearize_ranges`) the Jacobian blocks of one range of samples are computed (`linearize`) while
those of the range before are eliminated from them (`eliminate_blocks`): the same arithmetic in
the same order as the one fused pass, bit for bit (`smoothers._compiled.CompiledOps._eliminate_in_ranges`).
On an hour at 100 Hz the two take a quarter off the smoothers' wall time, for a sixth more CPU time.
"""
from __future__ import annotations

import threading

# A long recording's cost is computed as two ranges of samples on two threads (the kernels release
# the GIL). Where it is split depends on the number of samples alone, so the sum, and every result
# that depends on it, is the same on any machine.
SPLIT_MIN_SAMPLES = 8192


def cost_ranges(T: int) -> tuple[int, ...]:
    """The bounds of `smoothers._compiled_cost.range_cost`'s ranges for T samples."""
    return (0, T) if T < SPLIT_MIN_SAMPLES else (0, T // 2, T)


def run_beside(work, *args):
    """Start work(*args) on a new thread; returns the function that waits for it and returns what
    it returned or re-raises what it raised. A thread per call, not a pool: a pool's thread does not
    survive a fork."""
    raised, returned = [], []

    def target():
        try:
            returned.append(work(*args))
        except BaseException as exc:  # noqa: BLE001 - handed to the caller
            raised.append(exc)

    thread = threading.Thread(target=target, name="fusion-smoother-range", daemon=True)
    thread.start()

    def join():
        thread.join()
        if raised:
            raise raised[0]
        return returned[0]

    return join


# The linearisation of a long recording in ranges on two threads (`CompiledOps._eliminate_in_ranges`).
RANGE_SAMPLES = (8192, 12288)  # the smallest and the largest range


def linearize_ranges(T: int) -> list[int]:
    """The bounds of `CompiledOps._eliminate_in_ranges`'s ranges for T samples: eight or more ranges
    of 8,192 to 12,288 samples (`RANGE_SAMPLES`; two ranges' blocks take less memory than the
    trial's trajectory), or one range below 8 x 8,192 samples. Writing and reading the blocks takes
    about a quarter more CPU time than the one fused pass; only on long recordings does the overlap
    gain more wall time than that: one hour at 100 Hz, 27 % less wall time for the whole estimate
    (`bench_long.py` against `--one-thread`); BROAD trial 15, 52,556 samples in ranges of 6,569
    (measured while choosing this bound), 6 % less wall time for 25 % more CPU time. The results do
    not depend on the ranges."""
    size = min(max(T // 8, RANGE_SAMPLES[0]), RANGE_SAMPLES[1])
    return [0, T] if T < 8 * RANGE_SAMPLES[0] else [*range(0, T, size), T]

