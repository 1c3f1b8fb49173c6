"""Public datasets by name: listed, fetched and verified (`fusion data list`, `fusion data fetch`).

    from fusion.fetch import fetch
    report = fetch("broad")              # or "broad/03*", "repoimu/pendulum/*"; to=, mirror=
    print(report.summary())

Every file of a dataset is pinned: `data_registry.tsv` (shipped with the package) gives its URL at
one commit of the repository that publishes it and its git object id, the SHA-1 of
`b"blob <size>\\0" + content` (what `git hash-object FILE` prints), which names the right bytes
exactly. A download is streamed by `pooch` (Uieda et al., JOSS 5(45):1943, 2020) to a temporary
file beside its destination, checked against that id (and against the SHA-256 where the registry
has one) and only then moved into place; a file that differs is removed and reported. A file
verified once is remembered (its size and modification time, in `.fusion-fetch.json` in the
dataset's folder), so a second fetch downloads and hashes nothing.

Files land under one folder, `--to DIR`, else `$FUSION_DATA`, else the user cache
(`pooch.os_cache("fusion")`), in the layout the loaders read:

    DIR/broad/03_undisturbed_slow_rotation_C.hdf5   DIR/broad/trials.json   DIR/broad/LICENSE
    DIR/repoimu/pendulum/Pendulum_Test02a_Trial1_Segment_1.csv   DIR/repoimu/tstick/...

so that `--data-dir DIR --dataset 'broad/*'` reads them (and `--dataset 'broad/*'` alone finds
the cache, see `fusion.datasets.select`). A BROAD trial is published both as `.hdf5` and as
`.mat`; the `.hdf5` is fetched, the `.mat` only where the source holds no `.hdf5`.

A mirror (`mirror=` / `--mirror URL` / `$FUSION_MIRROR`) serves the same files at
`URL/<dataset>/<path>`, `path` as in the registry (`URL/broad/data_hdf5/03_....hdf5`).
An interrupted fetch leaves no partial file under a final name (pooch downloads to a temporary
file); running the command again fetches only what is missing. pooch does not continue a
partial download from its last byte: such a file is downloaded again.
"""
from __future__ import annotations

import csv
import fnmatch
import functools
import hashlib
import json
import os
import sys
import threading
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path

__all__ = ["DATASETS", "Dataset", "Entry", "FetchReport", "Item", "data_root", "fetch", "git_blob_sha1",
           "items", "list_datasets", "read_registry"]

REGISTRY = "data_registry.tsv"
STATE = ".fusion-fetch.json"  # per dataset folder: the files verified, by local name
MIRROR_ENV = "FUSION_MIRROR"
TIMEOUT_S = 30.0
SUPPORT_FILES = ("LICENSE", "README.md", "trials.json")


@dataclass(frozen=True)
class Dataset:
    """A public dataset the toolkit fetches by name."""

    name: str
    title: str
    licence: str
    citation: str
    repository: str
    commit: str


DATASETS: dict[str, Dataset] = {
    "broad": Dataset(
        "broad", "BROAD, Berlin Robust Orientation estimation Assessment Dataset (39 trials, optical truth)",
        "CC BY 4.0",
        "Laidig, Caruso, Cereatti, Seel: BROAD - A Benchmark for Robust Inertial Orientation Estimation. "
        "Data 6(7):72, 2021. doi:10.3390/data6070072",
        "https://github.com/dlaidig/broad", "7e2f8189bb4a3ac91eae32c69b6bc87f08a6e2ad"),
    "repoimu": Dataset(
        "repoimu", "RepoIMU, T-stick and three-segment pendulum with Vicon truth (95 recordings)",
        "none stated in the repository (cite the paper)",
        "Szczesna, Skurowski, Pruszowski, Peszor, Paszkuta, Wojciechowski: Reference Data Set for Accuracy "
        "Evaluation of Orientation Estimation Algorithms for Inertial Motion Capture Systems. ICCVG 2016, "
        "LNCS 9972, Springer",
        "https://github.com/agnieszkaszczesna/RepoIMU", "24145fc4778705177f3b6333dc2c967909240f9e"),
}


@dataclass(frozen=True)
class Entry:
    """One published file: a row of the registry."""

    dataset: str
    path: str  # in the publishing repository
    url: str  # at the pinned commit
    git_blob_sha1: str
    size: int | None  # bytes, where known
    sha256: str | None  # where known

    @property
    def local_name(self) -> str:
        """Its path below `DIR/<dataset>/` (see the module docstring)."""
        folder, _, name = self.path.rpartition("/")
        if self.dataset == "broad":
            return name  # data_hdf5/X.hdf5 and data_mat/X.mat sit side by side, as the loaders read them
        return f"{folder.lower()}/{name}" if folder else name


@dataclass(frozen=True)
class Item:
    """What a fetch asks for: one file, or one BROAD trial with its `.hdf5` and `.mat` (in the
    order they are tried)."""

    dataset: str
    key: str  # a trial's name, or a file's local name
    entries: tuple[Entry, ...]

    @property
    def support(self) -> bool:
        """A dataset's licence, readme or index rather than a recording."""
        return self.key in SUPPORT_FILES

    def matches(self, pattern: str) -> bool:
        """Whether a glob names it (case-insensitive, on its key or a file's local name)."""
        names = [self.key, *(e.local_name for e in self.entries)]
        return any(fnmatch.fnmatch(n.lower(), pattern.lower()) for n in names)


def read_registry(path: str | os.PathLike | None = None) -> list[Entry]:
    """The registry's rows (the packaged `data_registry.tsv` by default)."""
    if path is None:
        text = resources.files("fusion").joinpath(REGISTRY).read_text(encoding="utf-8")
        source = REGISTRY
    else:
        text = Path(path).read_text(encoding="utf-8")
        source = str(path)
    rows = list(csv.DictReader(text.splitlines(), delimiter="\t"))
    need = {"dataset", "path", "url", "git_blob_sha1"}
    if not rows or not need <= set(rows[0]):
        raise ValueError(f"{source}: not a dataset registry (need the columns {', '.join(sorted(need))})")
    return [Entry(r["dataset"], r["path"], r["url"], r["git_blob_sha1"].lower(),
                  int(r["bytes"]) if r.get("bytes") else None, r.get("sha256") or None) for r in rows]


def items(dataset: str, registry: list[Entry] | None = None) -> list[Item]:
    """What `fetch(dataset)` fetches: BROAD's 39 trials (`.hdf5`, else `.mat`), its `trials.json`
    and LICENSE; every RepoIMU file."""
    entries = [e for e in (registry if registry is not None else read_registry()) if e.dataset == dataset]
    if dataset != "broad":
        return [Item(dataset, e.local_name, (e,)) for e in entries]
    groups: dict[str, list[Entry]] = {}
    for e in entries:
        folder, _, name = e.path.rpartition("/")
        if folder in ("data_hdf5", "data_mat"):
            key = name if name == "trials.json" else name.rsplit(".", 1)[0]
        elif e.path == "LICENSE":
            key = "LICENSE"
        else:
            continue  # the repository's README: not data
        groups.setdefault(key, []).append(e)
    return [Item(dataset, key, tuple(sorted(group, key=lambda e: not e.path.startswith("data_hdf5/"))))
            for key, group in groups.items()]


def _resolve(name: str, registry: list[Entry]) -> tuple[str, list[Item]]:
    dataset, _, pattern = name.partition("/")
    dataset = dataset.lower()
    if dataset not in DATASETS:
        raise ValueError(f"unknown dataset {name!r}; fusion data list shows them: {', '.join(DATASETS)}")
    chosen = items(dataset, registry)
    if pattern and pattern != "*":
        named = [i for i in chosen if i.matches(pattern)]
        if not named:
            raise ValueError(f"{name!r} names no file of {dataset} (fusion data list shows the datasets)")
        chosen = named + [i for i in chosen if i.support and i not in named]  # the licence and index come along
    return dataset, chosen


def data_root(to: str | os.PathLike | None = None) -> Path:
    """Where datasets are fetched to: `to`, else `$FUSION_DATA`, else the user cache
    (`pooch.os_cache("fusion")`)."""
    if to:
        return Path(to)
    if os.environ.get("FUSION_DATA"):
        return Path(os.environ["FUSION_DATA"])
    return cache_dir()


def cache_dir() -> Path:
    """The user cache the datasets go to by default (`pooch.os_cache("fusion")`)."""
    import pooch

    return Path(pooch.os_cache("fusion"))


def git_blob_sha1(path: str | os.PathLike) -> str:
    """The git object id of a file: SHA-1 of `b"blob <size>\\0"` + its bytes (`git hash-object`)."""
    path = Path(path)
    digest = hashlib.sha1(b"blob %d\0" % path.stat().st_size)
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            digest.update(chunk)
    return digest.hexdigest()


class _State:
    """The files of one dataset folder verified before: {local name: [git id, size, mtime_ns]}.
    Written atomically (a temporary file renamed), merged with what another process wrote."""

    def __init__(self, folder: Path):
        self.path = folder / STATE
        self.known = self._read()
        self.new: dict[str, list] = {}
        self.lock = threading.Lock()

    def _read(self) -> dict[str, list]:
        try:
            doc = json.loads(self.path.read_text())
            return doc if isinstance(doc, dict) else {}
        except (OSError, ValueError):
            return {}

    def verified(self, name: str, path: Path, blob: str) -> bool:
        record = self.known.get(name)
        if not (isinstance(record, list) and len(record) == 3 and record[0] == blob):
            return False
        stat = path.stat()
        return record[1] == stat.st_size and record[2] == stat.st_mtime_ns

    def add(self, name: str, path: Path, blob: str) -> None:
        stat = path.stat()
        with self.lock:
            self.new[name] = [blob, stat.st_size, stat.st_mtime_ns]

    def save(self) -> None:
        if not self.new:
            return
        merged = {**self._read(), **self.new}
        tmp = self.path.with_name(f"{STATE}.{os.getpid()}.{threading.get_ident()}.tmp")
        try:
            tmp.write_text(json.dumps(merged, indent=0, sort_keys=True))
            os.replace(tmp, self.path)
        except OSError:  # a folder we cannot write to: the files are verified all the same, only hashed again next time
            tmp.unlink(missing_ok=True)


@dataclass
class Outcome:
    """What became of one item: `local` (verified before), `fetched`, `missing` (not at the
    source), `refused` (a download that is not the published file, removed), `offline`, `conflict`
    (a file of that name that is not the published one, left as it is), `failed`."""

    item: Item
    status: str
    path: Path | None = None
    url: str | None = None
    detail: str = ""
    bytes: int = 0


@dataclass
class FetchReport:
    dataset: str
    folder: Path
    source: str  # the mirror's URL, or "the pinned repository"
    outcomes: list[Outcome] = field(default_factory=list)

    def by(self, *status: str) -> list[Outcome]:
        return [o for o in self.outcomes if o.status in status]

    @property
    def ok(self) -> bool:
        return all(o.status in ("local", "fetched") for o in self.outcomes)

    def summary(self) -> str:
        """One line: what is in the folder now."""
        fetched, local = self.by("fetched"), self.by("local")
        size = sum(o.bytes for o in fetched) / 1e6
        here = [o for o in fetched + local if not o.item.support]
        support = [o for o in self.outcomes if o.item.support]
        also = (f" and {len(fetched) + len(local) - len(here)} of {len(support)} other files (licence, index)"
                if support else "")
        return (f"{self.dataset}: {len(here)} of {len(self.outcomes) - len(support)} recordings{also} verified in "
                f"{self.folder} ({len(fetched)} files fetched, {size:.1f} MB; {len(local)} already there)")

    def errors(self) -> list[str]:
        """One line per kind of failure, naming the files and what to do."""
        lines = []
        missing = self.by("missing")
        if missing:
            lines.append(f"{self.dataset}: {len(missing)} files not at {self.source} (fetch them from elsewhere, "
                         "or place them by hand): "
                         + ", ".join(o.item.key for o in missing))
        for o in self.by("refused", "conflict", "failed"):
            lines.append(f"{o.path}: {o.detail}")
        offline = self.by("offline")
        if offline:
            first = offline[0]
            more = f" (and {len(offline) - 1} other files)" if len(offline) > 1 else ""
            lines.append(f"cannot reach {first.url}{more}: {first.detail}; offline, download the files elsewhere and "
                         f"place them by hand in {first.path.parent} (named as in the URL), then run the fetch again")
        return lines


class _Bar:
    """A pooch progress bar (`total`, `update`, `reset`, `close`) that adds one file's bytes to a
    shared tqdm bar (several files download at once)."""

    def __init__(self, shared, lock: threading.Lock):
        self.shared, self.lock, self.done, self._total = shared, lock, 0, 0

    @property
    def total(self) -> int:
        return self._total

    @total.setter
    def total(self, value: int) -> None:
        self._total = int(value or 0)
        if self.shared is not None and self._total:  # counted when its download starts
            with self.lock:
                self.shared.total = (self.shared.total or 0) + self._total
                self.shared.refresh()

    def update(self, n: int) -> None:
        n = min(n, self._total - self.done) if self._total else n
        if n > 0:
            self.done += n
            if self.shared is not None:
                with self.lock:
                    self.shared.update(n)

    def reset(self) -> None:
        pass

    def close(self) -> None:
        pass


class _Verifying:
    """A pooch downloader that checks the temporary file's git object id before pooch moves it into
    place (pooch's own `known_hash` knows no git ids); a mismatch raises, and pooch removes the
    temporary file."""

    def __init__(self, entry: Entry, bar: _Bar):
        import pooch

        self.entry = entry
        self.http = pooch.HTTPDownloader(progressbar=bar, chunk_size=1 << 16, timeout=TIMEOUT_S)
        self.ran = False

    def __call__(self, url: str, output_file, pooch_obj) -> None:
        self.ran = True
        self.http(url, output_file, pooch_obj)
        name = output_file if isinstance(output_file, str) else output_file.name
        if hasattr(output_file, "flush"):
            output_file.flush()
        got = git_blob_sha1(name)
        if got != self.entry.git_blob_sha1:
            raise _Mismatch(f"downloaded from {url}, git object id {got}, not the published "
                            f"{self.entry.git_blob_sha1}: refused and removed")


class _Mismatch(ValueError):
    pass


@functools.cache
def _umask() -> int:
    """The process's umask (read by setting it and setting it back: `fetch` does it once, before
    its threads start)."""
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def local_path(folder: Path, local_name: str) -> Path:
    """Where a file of the dataset in `folder` is: `folder / local_name`, or the file there whose path
    differs only in case (RepoIMU as its repository publishes it: `Pendulum/`, where a fetch writes
    `pendulum/`), so that a copy laid out either way is found and not fetched twice."""
    path = folder / local_name
    if path.is_file() or not folder.is_dir():
        return path
    here = folder
    for part in Path(local_name).parts:
        names = {p.name.casefold(): p for p in here.iterdir()} if here.is_dir() else {}
        if part.casefold() not in names:
            return path
        here = names[part.casefold()]
    return here if here.is_file() else path


def _url(entry: Entry, mirror: str | None) -> str:
    return f"{mirror.rstrip('/')}/{entry.dataset}/{entry.path}" if mirror else entry.url


def _get(item: Item, folder: Path, state: _State, mirror: str | None, shared, lock) -> Outcome:
    """One item: verified where it is, else downloaded from its first source that has it."""
    for entry in item.entries:  # already here (in any of its forms)?
        path = local_path(folder, entry.local_name)
        if path.is_file():
            if state.verified(entry.local_name, path, entry.git_blob_sha1):
                return Outcome(item, "local", path)
            got = git_blob_sha1(path)
            if got == entry.git_blob_sha1:
                state.add(entry.local_name, path, got)
                return Outcome(item, "local", path)
            return Outcome(item, "conflict", path, detail=f"exists and is not the published file (git object id {got}, "
                                                          f"expected {entry.git_blob_sha1}); left as it is: move it "
                                                          "away to fetch the published one")
    import pooch
    import requests

    missing = None
    for entry in item.entries:
        path, url = folder / entry.local_name, _url(entry, mirror)
        downloader = _Verifying(entry, _Bar(shared, lock))
        try:
            pooch.retrieve(url, known_hash=f"sha256:{entry.sha256}" if entry.sha256 else None, fname=path.name,
                           path=path.parent, downloader=downloader)
        except _Mismatch as exc:
            return Outcome(item, "refused", path, url, str(exc))
        except ValueError as exc:  # pooch's SHA-256 check
            return Outcome(item, "refused", path, url, f"downloaded from {url}: {exc}; refused and removed")
        except requests.HTTPError as exc:
            code = exc.response.status_code if exc.response is not None else None
            if code in (403, 404, 410):
                missing = missing or Outcome(item, "missing", path, url, f"HTTP {code}")
                continue
            return Outcome(item, "failed", path, url, f"{url}: {exc}")
        except (requests.ConnectionError, requests.Timeout) as exc:
            return Outcome(item, "offline", path, url, type(exc).__name__)
        except requests.RequestException as exc:  # cut off mid-file: pooch removed the partial download
            return Outcome(item, "failed", path, url, f"download from {url} broke off ({type(exc).__name__}); "
                                                      "nothing kept: run the fetch again")
        if not downloader.ran:  # another process moved it into place meanwhile: check it as any file here
            got = git_blob_sha1(path)
            if got != entry.git_blob_sha1:
                return Outcome(item, "conflict", path, url, f"appeared while fetching and is not the published file "
                                                            f"(git object id {got}); left as it is")
        else:  # pooch's temporary file is private (0600): the user's umask, as for any file they create
            path.chmod(0o666 & ~_umask())
        state.add(entry.local_name, path, entry.git_blob_sha1)
        return Outcome(item, "fetched", path, url, bytes=path.stat().st_size)
    return missing


def fetch(name: str, to: str | os.PathLike | None = None, mirror: str | None = None, jobs: int = 4,
          progress: bool = False, registry: list[Entry] | None = None) -> FetchReport:
    """Fetch a dataset (`broad`), or the part of it a glob names (`broad/03*`,
    `repoimu/pendulum/*`), into `data_root(to)/<dataset>/`, verified file by file.

    mirror: a URL serving the files at `URL/<dataset>/<path>` (None: `$FUSION_MIRROR`, else the
        pinned repository). jobs: parallel downloads. progress: a progress bar on stderr.
    Returns a `FetchReport` (`ok`, `summary()`, `errors()`); raises ValueError for an unknown name.
    """
    import pooch

    registry = registry if registry is not None else read_registry()
    dataset, chosen = _resolve(name, registry)
    mirror = mirror or os.environ.get(MIRROR_ENV) or None
    folder = data_root(to) / dataset
    if folder.exists() and not folder.is_dir():
        raise ValueError(f"{folder}: exists and is not a folder")
    for path in {(folder / e.local_name).parent for i in chosen for e in i.entries}:
        path.mkdir(parents=True, exist_ok=True)  # here, not in the threads (which would race)
    pooch.get_logger().setLevel("WARNING")
    _umask()
    state = _State(folder)
    report = FetchReport(dataset, folder, f"{mirror.rstrip('/')}/{dataset}/" if mirror else DATASETS[dataset].repository)
    lock = threading.Lock()
    shared = None
    if progress:
        from tqdm import tqdm

        shared = tqdm(total=0, unit="B", unit_scale=True, desc=f"fetching {dataset}", file=sys.stderr, leave=False)
    try:
        pool = ThreadPoolExecutor(max_workers=max(1, jobs))
        try:
            report.outcomes = list(pool.map(lambda i: _get(i, folder, state, mirror, shared, lock), chosen))
        except BaseException:  # Ctrl-C: start no further download (those under way end, verified, or leave nothing)
            pool.shutdown(wait=False, cancel_futures=True)
            raise
        pool.shutdown()
    finally:
        if shared is not None:
            shared.close()
        state.save()
    return report


def list_datasets(to: str | os.PathLike | None = None, registry: list[Entry] | None = None) -> str:
    """A table: each dataset's name, files, size, licence, what is already in `data_root(to)`
    (files present; of them verified), and its citation."""
    registry = registry if registry is not None else read_registry()
    root = data_root(to)
    lines = [f"datasets in {root} (fusion data fetch NAME puts them there):"]
    for name, ds in DATASETS.items():
        chosen = items(name, registry)
        sizes = [next((e.size for e in i.entries if e.size), None) for i in chosen]
        known = [s for s in sizes if s]
        size = f"about {sum(known) / len(known) * len(sizes) / 1e6:.0f} MB" if known else "size unknown"
        folder = root / name
        state = _State(folder) if folder.is_dir() else None
        present = verified = 0
        for i in chosen:
            for e in i.entries:
                path = local_path(folder, e.local_name)
                if path.is_file():
                    present += 1
                    verified += bool(state and state.verified(e.local_name, path, e.git_blob_sha1))
                    break
        lines.append(f"  {name:<8} {len(chosen)} files, {size}; licence: {ds.licence}; local: {present} "
                     f"of {len(chosen)} ({verified} verified)")
        lines.append(f"  {'':<8} {ds.title}; {ds.repository} at {ds.commit[:12]}")
        lines.append(f"  {'':<8} cite: {ds.citation}")
    return "\n".join(lines)
