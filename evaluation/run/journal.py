"""The journal of a run: every finished job appended to the run's folder as it ends, so that a run
killed at any point (SIGKILL, the out-of-memory killer, a power cut) continues where it stopped.

    DIR/.fusion-run/journal.jsonl     while the run is going: a header line, then one line per job
    DIR/.fusion-run/parts/KEY.npz     the job's time series, when the run draws figures
    DIR/journal.jsonl                 after the run: the same journal, listed in the manifest

The header records the call that started the run (`call`: the keyword arguments of
`run_compare` or `run_ablate`), so `fusion compare --resume DIR` (or `run_resume(DIR)`) repeats
it: a job whose key is in the journal is not computed again, its row is read back as written.
A job's key is a hash of everything its result depends on: the recording's id and the contents
of its files (`fingerprint`), the estimator's label and the source of a user's estimator file,
and the run's options. A job whose recording changed since is computed again. A line is
written whole, flushed and synced (`os.fsync`), after the job's series file, so a line in the
journal always has its series; a half line left by a kill is ignored when reading back.
Failed jobs are journalled with their error and computed again on resume.

Like Optuna's journal storage and Ray Tune's experiment checkpoints, the journal holds what a
study needs to continue; unlike them it never holds the estimates themselves, only the rows.
"""
from __future__ import annotations

import hashlib
import json
import os
import shutil
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable

import numpy as np

RUN_DIR = ".fusion-run"  # in the output folder, the run in progress
JOURNAL = "journal.jsonl"
PARTS = "parts"
_FORMAT = "fusion-journal"
_VERSION = 1


def fingerprint(paths: Iterable[Path | None], what: str = "") -> str:
    """sha256 of the files (their names and contents; every file below a folder, in sorted order)
    a recording is read from; `what` (e.g. "sim") stands in for a recording without files."""
    digest = hashlib.sha256(what.encode())
    for path in paths:
        if path is None:
            continue
        path = Path(path)
        files = sorted(p for p in path.rglob("*") if p.is_file()) if path.is_dir() else [path]
        for f in files:
            digest.update(f.name.encode() + b"\0")
            with open(f, "rb") as handle:
                digest.update(hashlib.file_digest(handle, "sha256").digest())
    return digest.hexdigest()


def job_key(**parts: Any) -> str:
    """A short stable hash of the JSON of `parts` (sorted keys)."""
    text = json.dumps(parts, sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:24]


@dataclass
class Entry:
    """One journalled job: its key, row (as in results.json), error (None if it succeeded) and
    whether it wrote a series part."""

    key: str
    row: dict[str, Any]
    error: str | None = None
    part: bool = False


@dataclass
class Journal:
    """The journal of the run in `folder` (the output folder), opened for appending.

    `done` holds the entries read back (a resumed run), by key.
    """

    folder: Path
    header: dict[str, Any]
    done: dict[str, Entry] = field(default_factory=dict)
    _handle: Any = None

    @property
    def run_dir(self) -> Path:
        return self.folder / RUN_DIR

    @property
    def path(self) -> Path:
        return self.run_dir / JOURNAL

    def part_path(self, key: str) -> Path:
        return self.run_dir / PARTS / f"{key}.npz"

    @classmethod
    def start(cls, folder: Path, header: dict[str, Any], replace: bool = False) -> "Journal":
        """A new journal in `folder`. An unfinished one there is an error (`resume` continues it),
        or, with `replace`, discarded."""
        run_dir = Path(folder) / RUN_DIR
        if (run_dir / JOURNAL).is_file() and not replace:
            done = len(read(run_dir / JOURNAL)[1])
            raise ValueError(f"{folder}: holds an unfinished run ({done} jobs done); continue it with --resume "
                             f"{folder}, or give --overwrite to start afresh")
        if run_dir.exists():
            shutil.rmtree(run_dir)  # ours (a run killed before its first job), never the user's
        (run_dir / PARTS).mkdir(parents=True)
        journal = cls(Path(folder), {"format": _FORMAT, "version": _VERSION, **header})
        journal._open()
        journal._append(journal.header)
        return journal

    @classmethod
    def resume(cls, folder: Path) -> "Journal":
        """The unfinished journal in `folder`, its finished jobs read back, opened for appending."""
        path = Path(folder) / RUN_DIR / JOURNAL
        if not path.is_file():
            if (Path(folder) / JOURNAL).is_file():
                raise ValueError(f"{folder}: this run is complete (its journal is {Path(folder) / JOURNAL}); "
                                 "nothing to resume")
            raise FileNotFoundError(f"{path}: no unfinished run here to resume")
        header, entries = read(path)
        journal = cls(Path(folder), header)
        journal.done = {e.key: e for e in entries
                        if e.error is None and (not e.part or journal.part_path(e.key).is_file())}
        journal._open()
        return journal

    @staticmethod
    def read_header(folder: Path) -> dict[str, Any]:
        """The header of the unfinished run in `folder` (see `resume`)."""
        path = Path(folder) / RUN_DIR / JOURNAL
        if not path.is_file():
            Journal.resume(folder)  # raises the message that fits
        return read(path)[0]

    def _open(self) -> None:
        self._handle = open(self.path, "a", encoding="utf-8")

    def _append(self, doc: dict[str, Any]) -> None:
        self._handle.write(json.dumps(doc, separators=(",", ":")) + "\n")
        self._handle.flush()
        os.fsync(self._handle.fileno())

    def record(self, key: str, row: dict[str, Any], error: str | None, part: dict[str, np.ndarray] | None) -> None:
        """Journal one finished job (its series part first, written whole under a temporary name)."""
        if part is not None:
            path = self.part_path(key)
            tmp = path.with_name(f".{path.name}.tmp")
            with open(tmp, "wb") as handle:
                np.savez(handle, **part)
                handle.flush()
                os.fsync(handle.fileno())
            os.replace(tmp, path)
        self._append({"key": key, "row": row, "error": error, "part": part is not None})

    def load_part(self, key: str) -> dict[str, np.ndarray]:
        with np.load(self.part_path(key), allow_pickle=False) as z:
            return {k: z[k] for k in z.files}

    def close(self) -> None:
        if self._handle is not None:
            self._handle.close()
            self._handle = None

    def finish(self, stage: Path) -> None:
        """Copy the journal into the staging folder (it is committed with the run's files)."""
        self.close()
        shutil.copyfile(self.path, stage / JOURNAL)

    def remove(self) -> None:
        """After the run's files were committed: the run in progress is gone."""
        self.close()
        shutil.rmtree(self.run_dir, ignore_errors=True)


def read(path: Path) -> tuple[dict[str, Any], list[Entry]]:
    """A journal's header and entries (a half-written last line, left by a kill, is ignored);
    anything else that is not what fusion writes is one line naming the file."""
    try:
        lines = path.read_text(encoding="utf-8").split("\n")
    except (OSError, UnicodeDecodeError) as exc:
        raise ValueError(f"{path}: not a readable journal ({type(exc).__name__})") from None
    complete = lines[:-1]  # every line fusion finished ends with a newline
    try:
        header = json.loads(complete[0]) if complete else None
    except ValueError:
        header = None
    if not isinstance(header, dict) or header.get("format") != _FORMAT:
        raise ValueError(f"{path}: not a fusion journal")
    if header.get("version") != _VERSION:
        raise ValueError(f"{path}: journal version {header.get('version')!r}, this fusion reads {_VERSION}")
    entries = []
    for number, line in enumerate(complete[1:], start=2):
        try:
            doc = json.loads(line)
            entries.append(Entry(str(doc["key"]), dict(doc["row"]), doc.get("error"), bool(doc.get("part"))))
        except (ValueError, KeyError, TypeError) as exc:
            raise ValueError(f"{path}: line {number} is not a journal entry ({type(exc).__name__}); "
                             "remove the file's .fusion-run folder to start afresh") from None
    return header, entries
