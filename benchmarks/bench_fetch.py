"""`fusion data fetch broad` from a local mirror holding only the BROAD trials of a data folder.

    python benchmarks/bench_fetch.py [--data ../shared/data] [--trials 3]

Serves `<data>/broad` (its trials, `trials.json` and LICENSE) over HTTP from a thread, laid out as
the registry says (`URL/broad/data_hdf5/<trial>.hdf5`, `URL/broad/data_mat/<trial>.mat`), then
measures, through the `fusion` command:

1. a fetch into a fresh folder: the trials the mirror holds fetched and verified, the others named
   in one line, exit 1;
2. a second fetch: nothing downloaded (the server's GET count) and its time;
3. a corrupted trial on the mirror: refused, nothing left under its name;
4. `fusion compare --estimators ekf` on a few of the fetched trials against the same trials in
   the data folder: the scores must be identical.

Prints the figures; exits 1 if any of them is not what is expected.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

from http_mirror import Mirror  # noqa: E402  (the fetch tests' local mirror)

FUSION = [sys.executable, "-m", "fusion"]


def lay_out(broad: Path, mirror: Path) -> list[str]:
    """Links to `broad`'s files where the registry puts them; returns the trials' names."""
    trials = []
    for path in sorted(broad.iterdir()):
        if path.suffix in (".hdf5", ".mat"):
            target = mirror / "broad" / ("data_hdf5" if path.suffix == ".hdf5" else "data_mat") / path.name
            trials.append(path.stem)
        elif path.name == "trials.json":
            target = mirror / "broad" / "data_hdf5" / path.name
        elif path.name == "LICENSE":
            target = mirror / "broad" / path.name
        else:
            continue
        target.parent.mkdir(parents=True, exist_ok=True)
        target.symlink_to(path.resolve())
    return trials


def run(args: list[str]) -> tuple[int, str, str, float]:
    start = time.perf_counter()
    proc = subprocess.run(FUSION + args, capture_output=True, text=True, env={**os.environ, "FUSION_MIRROR": ""})
    return proc.returncode, proc.stdout, proc.stderr, time.perf_counter() - start


def scores(json_path: Path) -> list[tuple]:
    doc = json.loads(json_path.read_text())
    return [(r["dataset"], r["estimator"], r["samples"], r["scored_samples"], r["rmse_deg"], r["max_deg"])
            for r in doc["results"]]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", default=os.environ.get("FUSION_DATA", "../shared/data"))
    parser.add_argument("--trials", type=int, default=3, help="trials compared (default: 3)")
    args = parser.parse_args()
    data = Path(args.data)
    failures = []
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        trials = lay_out(data / "broad", tmp / "mirror")
        mirror = Mirror(tmp / "mirror")
        url, gets = mirror.url, mirror.requests
        fetched = tmp / "fetched"

        code, out, err, seconds = run(["data", "fetch", "broad", "--mirror", url, "--to", str(fetched), "--no-progress"])
        size = sum(p.stat().st_size for p in (fetched / "broad").iterdir()) / 1e6
        print(f"first fetch: exit {code}, {seconds:.2f} s, {len(gets)} GETs, {size:.1f} MB in {fetched / 'broad'}")
        print(f"  {out.strip()}")
        print(f"  {err.strip()[:300]}{' ...' if len(err.strip()) > 300 else ''}")
        missing = err.strip().rsplit(": ", 1)[-1].split(", ") if err.strip() else []
        if code != 1 or f"{len(trials)} of 39 recordings" not in out or len(missing) != 39 - len(trials) \
                or len(err.strip().splitlines()) != 1:
            failures.append("first fetch: expected the shared trials fetched and the others named in one line, exit 1")

        held = {"/" + p.relative_to(tmp / "mirror").as_posix() for p in (tmp / "mirror").rglob("*") if p.is_file()}
        gets.clear()
        code, out, err, seconds = run(["data", "fetch", "broad", "--mirror", url, "--to", str(fetched), "--no-progress"])
        again = [g for g in gets if g in held]
        print(f"second fetch: exit {code}, {seconds:.2f} s (the command's start-up included); {len(gets)} GETs, "
              f"{len(again)} of them for files the mirror holds (the rest: the missing trials asked for again)")
        print(f"  {out.strip()}")
        if again or "0 files fetched" not in out:
            failures.append(f"the second fetch downloaded {again}")

        hdf5 = next(t for t in trials if (tmp / "mirror" / "broad" / "data_hdf5" / f"{t}.hdf5").exists())
        link = tmp / "mirror" / "broad" / "data_hdf5" / f"{hdf5}.hdf5"
        data_bytes = bytearray(link.read_bytes())
        data_bytes[len(data_bytes) // 2] ^= 0xFF
        link.unlink()
        link.write_bytes(bytes(data_bytes))
        corrupt = tmp / "corrupt"
        code, out, err, seconds = run(["data", "fetch", f"broad/{hdf5}", "--mirror", url, "--to", str(corrupt),
                                       "--no-progress"])
        left = (corrupt / "broad" / f"{hdf5}.hdf5").exists()
        print(f"corrupted {hdf5}.hdf5 on the mirror: exit {code}; file left: {left}; {err.strip()[:240]}")
        if code != 1 or left or "refused and removed" not in err:
            failures.append("the corrupted file was not refused")
        mirror.close()

        chosen = ",".join(f"broad/{t}" for t in trials[: args.trials])
        results = {}
        for name, folder in (("shared", data), ("fetched", fetched)):
            path = tmp / f"{name}.json"
            code, out, err, seconds = run(["compare", "--estimators", "ekf", "--dataset", chosen, "--data-dir",
                                           str(folder), "--json", str(path), "--jobs", "1", "--no-progress"])
            results[name] = scores(path) if code == 0 else None
            print(f"compare ekf on {args.trials} trials, --data-dir {folder}: exit {code}, {seconds:.1f} s")
        same = results["shared"] is not None and results["shared"] == results["fetched"]
        for row in results["fetched"] or []:
            print(f"  {row[0]:<45} {row[1]}  total RMSE {row[4]['total']:.4f} deg, inclination "
                  f"{row[4]['inclination']:.4f} deg")
        print(f"scores identical to the data folder's: {same}")
        if not same:
            failures.append("the fetched trials score differently")
    for failure in failures:
        print(f"FAILED: {failure}")
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
