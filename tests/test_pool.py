"""The worker pool (`fusion.evaluation.run.pool`): outcomes as tasks finish, a task's exception
rebuilt in the parent, a task past its time limit stopped, a dead worker replaced, and no
worker left after the pool, however it ends."""
from __future__ import annotations

import os
import signal
import sys

import pytest

from cluster_fixtures import alive
from fusion.evaluation.run.pool import TaskTimeout, WorkerDied, WorkerPool

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")


def square(x: int) -> int:
    return x * x


def fail(message: str) -> None:
    raise ValueError(message)


def hang(path: str) -> None:
    open(path, "w").close()  # say it started
    signal.pause()


def die() -> None:
    os.kill(os.getpid(), signal.SIGKILL)


def hang_or_square(path: str, x: int) -> int:
    if path:
        hang(path)
    return square(x)


def die_or_square(kill: bool, x: int) -> int:
    if kill:
        die()
    return square(x)


def pid() -> int:
    return os.getpid()


def test_outcomes_come_back_with_their_index():
    with WorkerPool(2) as pool:
        out = dict(pool.imap_unordered(square, [(k,) for k in range(10)]))
    assert {k: o.result() for k, o in out.items()} == {k: k * k for k in range(10)}


def test_a_task_exception_is_raised_in_the_parent_as_it_was():
    with WorkerPool(1) as pool:
        ((index, outcome),) = list(pool.imap_unordered(fail, [("bad input: file x",)]))
    assert index == 0 and isinstance(outcome.error, ValueError)
    with pytest.raises(ValueError, match="bad input: file x"):
        outcome.result()
    assert "raise ValueError(message)" in outcome.trace


def test_a_task_past_its_limit_is_stopped_and_the_pool_goes_on(tmp_path):
    started = tmp_path / "started"
    with WorkerPool(1, timeout_s=0.5) as pool:
        out = dict(pool.imap_unordered(hang_or_square, [(str(started), 2), ("", 3)]))
    assert isinstance(out[0].error, TaskTimeout) and "0.5 s" in str(out[0].error)
    assert out[1].result() == 9  # the replacement worker ran the next task
    assert started.exists()


def test_a_dead_worker_fails_its_task_only():
    with WorkerPool(1) as pool:
        out = dict(pool.imap_unordered(die_or_square, [(True, 2), (False, 4)]))
    assert isinstance(out[0].error, WorkerDied) and "signal 9" in str(out[0].error)
    assert out[1].result() == 16


def test_no_worker_is_left_after_an_exception_in_the_parent():
    pids = []
    with pytest.raises(KeyboardInterrupt):
        with WorkerPool(2) as pool:
            for _, outcome in pool.imap_unordered(pid, [(), ()]):
                pids.append(outcome.result())
            pids += [w.process.pid for w in pool._workers]
            raise KeyboardInterrupt  # as Ctrl-C or SIGTERM would, mid-run
    assert pids and not [p for p in pids if alive(p)]  # killed and reaped before the exception went on
