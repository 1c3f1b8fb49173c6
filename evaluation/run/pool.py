"""A small process pool that can always be stopped: the worker processes of `fusion compare`,
`fusion ablate` and the report's figures.

    with WorkerPool(2, initializer, (state,)) as pool:
        for index, outcome in pool.imap_unordered(task, [(a,), (b,)]):
            ...

Why not `concurrent.futures.ProcessPoolExecutor`: its feeder and manager threads can leave the
parent blocked on a lock after its workers were terminated (a SIGTERM during a sweep that never
exits), and its workers outlive a parent that is killed outright. Here there are no threads:
one pipe per worker, one task in flight per worker, and the parent waits on the pipes and the
processes' sentinels together (`multiprocessing.connection.wait`). So:

- stopping is killing: on an exception in the parent (a job's error, Ctrl-C, SIGTERM raised as
  an exception by the command line) every worker gets SIGKILL and is reaped before the
  exception goes on;
- workers die with their parent even when the parent is killed outright (SIGKILL, the
  out-of-memory killer) or is a library caller that never cleans up: on Linux each worker asks
  the kernel for SIGKILL when its parent dies (`prctl(PR_SET_PDEATHSIG)`), and every worker also
  exits when its pipe to the parent closes;
- a task may have a time limit: past it, its worker is killed and replaced, and the task's
  outcome is a `TaskTimeout`;
- a worker that dies mid-task (a segfault, the OOM killer) gives that task a `WorkerDied`
  outcome; the pool replaces it and goes on.

Outcomes come back as they finish, as (task index, `Outcome`). Workers are forked where the
platform can fork (they inherit the parent's imports and state, so a task needs to carry no
more than indices); elsewhere spawned, and then the initializer, its arguments and the tasks
must be picklable.
"""
from __future__ import annotations

import multiprocessing
import os
import signal
import sys
import time
import traceback
from dataclasses import dataclass
from multiprocessing.connection import Connection, wait
from typing import Any, Callable, Iterable, Iterator, Sequence


def default_jobs() -> int:
    """All the cores this process may use."""
    try:
        return max(len(os.sched_getaffinity(0)), 1)
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


def pool_context() -> multiprocessing.context.BaseContext:
    """'fork' where available (workers inherit the parent's imports and registered estimators),
    else 'spawn'."""
    methods = multiprocessing.get_all_start_methods()
    return multiprocessing.get_context("fork" if "fork" in methods else "spawn")


@dataclass(frozen=True)
class Outcome:
    """What a task gave: `value` when it returned, else `error` (the exception, rebuilt in the
    parent; a `RuntimeError` with the text when it could not be sent) and `trace` (the
    worker's traceback text, for debugging)."""

    value: Any = None
    error: BaseException | None = None
    trace: str = ""

    def result(self) -> Any:
        """The value, or the task's exception raised here."""
        if self.error is not None:
            raise self.error
        return self.value


class TaskTimeout(Exception):
    """A task ran past the pool's time limit; its worker was killed."""


class WorkerDied(Exception):
    """A worker process died while running a task (killed, crashed, out of memory)."""


# Signals that mean the process crashed by itself (a fault in compiled code: an extension module,
# ctypes, numba), as against being killed from outside.
CRASH_SIGNALS = {"SIGSEGV", "SIGBUS", "SIGILL", "SIGFPE", "SIGABRT"}


def death_text(exitcode: int | None) -> str:
    """How a worker process that died mid-task ended, in words (`WorkerDied`'s text): its exit
    status (`os._exit`, or the interpreter stopping) or the signal that ended it, with what the
    signal usually means."""
    if exitcode is None:
        return "the worker process running it died (how is unknown)"
    if exitcode >= 0:
        return (f"the worker process running it exited with status {exitcode} (os._exit, or the interpreter "
                "stopped) before returning")
    try:
        name = signal.Signals(-exitcode).name
    except ValueError:
        name = f"signal {-exitcode}"
    if name in CRASH_SIGNALS:
        why = "a crash in compiled code it ran, e.g. a segmentation fault in an extension or ctypes call"
    elif name == "SIGKILL":
        why = "killed from outside: out of memory?"
    else:
        why = "killed from outside"
    return f"the worker process running it was killed by signal {-exitcode} ({name}: {why})"


def _die_with_parent(parent_pid: int) -> None:
    """Ask the kernel to SIGKILL this process when its parent dies (Linux); exit now if the
    parent is already gone."""
    if sys.platform.startswith("linux"):
        import ctypes

        try:
            libc = ctypes.CDLL(None, use_errno=True)
            libc.prctl(1, signal.SIGKILL, 0, 0, 0)  # PR_SET_PDEATHSIG = 1 (prctl(2))
        except (OSError, AttributeError):
            pass
    if os.getppid() != parent_pid:  # the parent died before the request was made
        os._exit(1)


def _worker_main(conn: Connection, parent_pid: int, initializer: Callable | None, initargs: tuple) -> None:
    """A worker: signals as `quiet_worker`, then tasks from the pipe until None or EOF."""
    _die_with_parent(parent_pid)
    quiet_worker()
    if initializer is not None:
        initializer(*initargs)
    while True:
        try:
            message = conn.recv()
        except (EOFError, OSError):  # the parent closed its end or died
            break
        if message is None:
            break
        fn, args = message
        try:
            reply = Outcome(fn(*args))
        except BaseException as exc:  # every failure goes back to the parent as an outcome
            reply = Outcome(error=exc, trace=traceback.format_exc())
        try:
            conn.send(reply)
        except Exception as exc:  # the value or the exception would not pickle
            conn.send(Outcome(error=RuntimeError(f"{type(exc).__name__} sending a task's outcome: {exc}"),
                              trace=reply.trace))
    conn.close()
    os._exit(0)  # no atexit handlers or inherited clean-up of the parent's state


def quiet_worker() -> None:
    """In a worker: Ctrl-C goes to the whole process group, but only the parent acts on it (it
    stops the workers); SIGTERM kills (a forked worker would otherwise inherit the parent's
    handler). A worker that crashes (a segfault in compiled code a user's estimator calls) is
    reported by the parent in one line (`death_text`): the fault handler a forked worker inherits
    (Python's `-X faulthandler`, pytest's) would print its own dump of every thread besides."""
    import faulthandler

    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    faulthandler.disable()


class _Worker:
    def __init__(self, ctx: multiprocessing.context.BaseContext, initializer: Callable | None, initargs: tuple) -> None:
        self.conn, child = ctx.Pipe(duplex=True)
        self.process = ctx.Process(target=_worker_main, args=(child, os.getpid(), initializer, initargs), daemon=True)
        self.process.start()
        child.close()
        self.task: int | None = None
        self.started = 0.0

    def kill(self) -> None:
        if self.process.is_alive():
            self.process.kill()
        self.process.join()
        self.conn.close()


class WorkerPool:
    """`processes` worker processes, each running `initializer(*initargs)` once (a context manager;
    leaving it stops every worker: gracefully after a normal end, by SIGKILL after an exception)."""

    def __init__(self, processes: int, initializer: Callable | None = None, initargs: tuple = (),
                 timeout_s: float | None = None) -> None:
        if processes < 1:
            raise ValueError(f"a pool needs at least one process, got {processes}")
        self._ctx = pool_context()
        self._init = (initializer, initargs)
        self.timeout_s = timeout_s
        self._workers: list[_Worker] = []
        self._size = processes

    def __enter__(self) -> "WorkerPool":
        try:
            self._workers = [_Worker(self._ctx, *self._init) for _ in range(self._size)]
        except BaseException:
            self.kill()
            raise
        return self

    def __exit__(self, exc_type: Any, *exc: Any) -> bool:
        if exc_type is None:
            self.close()
        else:
            self.kill()
        return False

    def close(self) -> None:
        """Ask idle workers to exit and reap them (a worker still busy is killed)."""
        for w in self._workers:
            try:
                if w.task is None:
                    w.conn.send(None)
            except OSError:
                pass
        for w in self._workers:
            w.process.join(timeout=5)
            w.kill()
        self._workers = []

    def kill(self) -> None:
        """SIGKILL every worker and reap it: nothing is left running."""
        for w in self._workers:
            if w.process.is_alive():
                w.process.kill()
        for w in self._workers:
            w.kill()
        self._workers = []

    def imap_unordered(self, fn: Callable, args: Iterable[tuple]) -> Iterator[tuple[int, Outcome]]:
        """`fn(*a)` for every `a` of `args` on the workers; yields (index into args, `Outcome`) as
        each finishes. Tasks are sent to idle workers only, one at a time, so a task not started
        is never lost to a dead worker."""
        pending = list(enumerate(args))[::-1]  # popped from the end: the first task first
        while pending or any(w.task is not None for w in self._workers):
            for w in self._workers:
                if w.task is None and pending:
                    index, a = pending.pop()
                    w.conn.send((fn, a))
                    w.task, w.started = index, time.monotonic()
            busy = [w for w in self._workers if w.task is not None]
            ready = wait([w.conn for w in busy] + [w.process.sentinel for w in busy], timeout=self._wait_s(busy))
            for w in busy:
                index = w.task
                if w.conn in ready:
                    try:
                        outcome = w.conn.recv()
                    except (EOFError, OSError):  # it died while sending
                        outcome = self._replace(w, WorkerDied(self._death(w)))
                    else:
                        w.task = None
                    yield index, outcome
                elif w.process.sentinel in ready:
                    yield index, self._replace(w, WorkerDied(self._death(w)))
                elif self.timeout_s is not None and time.monotonic() - w.started > self.timeout_s:
                    yield index, self._replace(w, TaskTimeout(f"still running after {self.timeout_s:g} s; stopped"))

    def _wait_s(self, busy: Sequence[_Worker]) -> float | None:
        if self.timeout_s is None or not busy:
            return None
        return max(0.0, min(w.started for w in busy) + self.timeout_s - time.monotonic()) + 0.01

    def _death(self, w: _Worker) -> str:
        w.process.join(timeout=1)
        return death_text(w.process.exitcode)

    def _replace(self, w: _Worker, error: BaseException) -> Outcome:
        w.kill()
        self._workers[self._workers.index(w)] = _Worker(self._ctx, *self._init)
        return Outcome(error=error)
