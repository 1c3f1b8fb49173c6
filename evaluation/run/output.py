"""Output folders of `fusion compare --out DIR`, `fusion ablate --out DIR` and `fusion report DIR`:
the lock, the staging folder and the manifest, so that only files the toolkit wrote are ever
replaced or removed and an interrupted run leaves the folder as it was (`OutputFolder`).
What goes into the folder is `fusion.evaluation.report.render`'s business.
"""
from __future__ import annotations

import json
import os
import shutil
import signal
from pathlib import Path
from typing import Any

RESULTS = "results.json"  # the last file moved in: a folder with it is complete


MANIFEST = ".fusion-manifest.json"
LOCK = ".fusion.lock"
STAGING_PREFIX = ".fusion-staging-"
_MANIFEST_FORMAT = "fusion-output-manifest"


class OutputFolder:
    """An output folder held by one run (a context manager).

    - Lock: `DIR/.fusion.lock`, held with `fcntl.flock` for the whole run (the PID inside is
      for the message only). A second run on the folder is refused with one line; the kernel
      releases the lock when a run dies, however it dies, so a crash never leaves it stuck. A run
      that ends removes the file (while it still holds the lock; a run that opened it just before
      sees that the path no longer names the file it locked, and opens it afresh), so a finished
      folder holds no lock file.
    - Staging: the run writes into `DIR/.fusion-staging-XXXX/`; on an error, SIGINT or SIGTERM
      that folder is removed and DIR is as it was. Staging folders left by a killed run
      (SIGKILL) are removed by the next run that holds the lock.
    - Commit (`commit`): with SIGINT/SIGTERM held back until it is done, results.json is
      removed first, the files of the previous run (those in `DIR/.fusion-manifest.json`) that
      the new run regenerates but does not write again are removed, the staged files are moved in
      (`os.replace`: each file is whole), the manifest is written, and results.json is moved in
      last. So a folder with results.json is complete; only files listed in the manifest are ever
      removed, and a staged file would never replace a file the toolkit did not write (an error
      instead). A folder written before manifests existed has its files overwritten, never removed.
      A re-render (`fusion report`) regenerates only what it draws (`regenerates`): the run's
      results, series, journal and exported trajectories stay as they are.
    """

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self.staging: Path | None = None
        self._fd: int | None = None

    def __enter__(self) -> "OutputFolder":
        import tempfile

        out = self.path
        if out.exists() and not out.is_dir():
            raise ValueError(f"{out}: exists and is not a folder")
        out.mkdir(parents=True, exist_ok=True)
        self._fd = _lock(out)
        try:
            for stale in out.glob(STAGING_PREFIX + "*"):  # left by a killed run; we hold the lock
                if stale.is_dir() and not stale.is_symlink():
                    shutil.rmtree(stale, ignore_errors=True)
            self.staging = Path(tempfile.mkdtemp(prefix=STAGING_PREFIX, dir=out))
        except BaseException:
            self._release()
            raise
        return self

    def __exit__(self, *exc: Any) -> bool:
        if self.staging is not None:
            shutil.rmtree(self.staging, ignore_errors=True)
            self.staging = None
        self._release()
        return False

    def _release(self) -> None:
        if self._fd is not None:
            try:
                os.unlink(self.path / LOCK)  # still held: no other run can have it (`_lock` checks the path)
            except OSError:
                pass
            os.close(self._fd)  # closing the descriptor releases the flock
            self._fd = None

    def manifest(self) -> list[str] | None:
        """The files (relative paths) the toolkit wrote here, None if there is no manifest."""
        return read_manifest(self.path)

    def holds_run(self) -> bool:
        """Whether the folder holds the results of a finished run (results.json, or files the
        toolkit listed in its manifest)."""
        return (self.path / RESULTS).exists() or bool(self.manifest())

    def commit(self, regenerates: tuple[str, ...] | None = None) -> None:
        """Move the staged files in (see the class docstring).

        regenerates: the files this commit writes afresh, as relative paths and folder prefixes
            ending in "/" (`fusion report`: `report.RENDERED`); a file of the previous run outside
            them is kept. None: a whole run, which replaces every file of the previous run.
        """
        out, stage = self.path, self.staging
        staged = sorted(p.relative_to(stage).as_posix() for p in stage.rglob("*") if p.is_file())
        old = self.manifest()
        legacy = old is None and (out / RESULTS).exists()
        owned = set(old or [])
        if not legacy:
            clash = [rel for rel in staged if (out / rel).exists() and rel not in owned]
            if clash:
                raise ValueError(f"{out / clash[0]}: exists and was not written by fusion; move it away or choose "
                                 "another output folder (nothing was changed)")

        def regenerated(rel: str) -> bool:
            return regenerates is None or any(rel == r or (r.endswith("/") and rel.startswith(r))
                                              for r in regenerates)

        outside = [rel for rel in staged if not regenerated(rel)]
        if outside:  # a partial commit replaces only what it regenerates
            raise ValueError(f"{out}: {outside[0]} is not among the files this command rewrites (nothing was changed)")
        keep = [rel for rel in owned if not regenerated(rel) and (out / rel).is_file()]
        with _signals_held():
            if RESULTS in staged and (out / RESULTS).exists():
                (out / RESULTS).unlink()  # from here until the end the folder reads as incomplete
            for rel in sorted(owned):
                target = out / rel
                if regenerated(rel) and rel not in staged and target.is_file() and not target.is_symlink():
                    target.unlink()
            for rel in staged:
                if rel != RESULTS:
                    (out / rel).parent.mkdir(parents=True, exist_ok=True)
                    os.replace(stage / rel, out / rel)
            files = sorted(set(staged) | set(keep))
            _atomic_text(out / MANIFEST, json.dumps({"format": _MANIFEST_FORMAT, "files": files}, indent=1) + "\n")
            if RESULTS in staged:
                os.replace(stage / RESULTS, out / RESULTS)


def read_manifest(out: Path) -> list[str] | None:
    """`DIR/.fusion-manifest.json`'s file list (None without one); a broken one is an error."""
    path = Path(out) / MANIFEST
    if not path.is_file():
        return None
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
        files = doc["files"]
        if doc.get("format") != _MANIFEST_FORMAT or not all(isinstance(f, str) for f in files):
            raise TypeError("not a fusion manifest")
    except (ValueError, KeyError, TypeError, RecursionError, UnicodeDecodeError) as exc:
        raise ValueError(f"{path}: not a readable fusion manifest ({type(exc).__name__}); delete it to start afresh") from None
    # Only plain relative paths inside the folder: a hand-edited manifest must not reach outside.
    return [f for f in files if f and not Path(f).is_absolute() and ".." not in Path(f).parts]


def _lock(out: Path) -> int | None:
    try:
        import fcntl
    except ImportError:  # not on a POSIX system: no lock
        return None
    while True:
        fd = os.open(out / LOCK, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            holder = os.read(fd, 32).decode("ascii", "replace").strip()
            os.close(fd)
            raise ValueError(f"{out}: in use by another fusion run (pid {holder or 'unknown'}); wait for it to finish "
                             "or choose another output folder") from None
        try:
            if os.fstat(fd).st_ino == os.stat(out / LOCK).st_ino:
                break  # the file we locked is the one the path names
        except FileNotFoundError:
            pass
        os.close(fd)  # removed by the run that held it as we opened it: lock the new one
    os.ftruncate(fd, 0)
    os.write(fd, f"{os.getpid()}\n".encode())
    return fd


class _signals_held:
    """SIGINT and SIGTERM wait until the block is done (then raise KeyboardInterrupt), so a
    commit is never cut in half by them (only the main thread can set handlers; elsewhere a no-op)."""

    def __enter__(self) -> None:
        import threading

        self.caught: list[int] = []
        self.old: dict[int, Any] = {}
        if threading.current_thread() is threading.main_thread():
            for sig in (signal.SIGINT, signal.SIGTERM):
                self.old[sig] = signal.signal(sig, lambda signum, frame: self.caught.append(signum))

    def __exit__(self, *exc: Any) -> bool:
        for sig, handler in self.old.items():
            signal.signal(sig, handler)
        if self.caught and exc[0] is None:
            raise KeyboardInterrupt
        return False


def _atomic_text(path: Path, text: str) -> None:
    """Write `path` under a temporary name in the same folder, then rename: never half a file."""
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    tmp.write_text(text, encoding="utf-8")
    os.replace(tmp, path)


