"""What every tutorial notebook shares: which recording it runs on, said out loud.

The notebooks read the course recordings from the data directory the toolkit uses everywhere
(`$FUSION_DATA`, else `./data`; `python docs/build_tutorial.py --data-dir DIR` sets
`$FUSION_DATA` for the notebooks it runs). Without any recordings they fall back to `sim`, the
built-in simulated recording, and print that they did: the numbers then differ from the ones
quoted in the text. With `$FUSION_DATA` set but the recording missing they stop with an error:
a wrong data path must not quietly turn a lesson on real data into one on simulated data.
"""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np

import fusion
from fusion import datasets
from fusion.types import ImuSamples, Recording

SIM = datasets.SIM_ID


def fusion_source() -> Path:
    """The folder the `fusion` package is imported from (the code these notebooks teach)."""
    return Path(fusion.__file__).resolve().parent


def load_recording(preferred: str = "ece276a/1") -> Recording:
    """The recording `preferred` from the data directory, else `sim` (see the module docstring).

    Prints one line naming what was loaded and from where, and where `fusion` was imported from.
    """
    root = datasets.data_dir_from(None)
    found = datasets.discover(root)
    if preferred in found:
        recording = datasets.load(preferred, root)
        origin = f"from {root.resolve()}"
    elif os.environ.get("FUSION_DATA"):
        real = [rid for rid in found if rid != SIM]
        raise FileNotFoundError(
            f"FUSION_DATA={os.environ['FUSION_DATA']} is set, but it holds no recording {preferred!r} "
            f"(found: {', '.join(real) or 'none'}); point FUSION_DATA at the shared data folder"
        )
    else:
        print(f"NOTE: no recording {preferred!r} under {root.resolve()} and FUSION_DATA is not set: this "
              f"notebook runs on '{SIM}', the built-in simulated recording. Its numbers differ from those "
              "quoted in the text.")
        recording = datasets.load(SIM)
        origin = "(simulated)"
    imu = recording.imu
    print(f"{recording.id}: {len(imu)} IMU samples, {imu.t[-1] - imu.t[0]:.1f} s, "
          f"{'with' if recording.truth is not None else 'without'} ground truth {origin}")
    print(f"fusion imported from {fusion_source()}")
    return recording


def fetched_trial(name: str = "broad/01*", fetch_now: bool = False) -> Recording:
    """A public dataset's recording found by name, as `fusion compare --dataset NAME` finds it: in
    the data directory (`$FUSION_DATA`: the shared folder holds fourteen BROAD trials), else in the
    folder `fusion data fetch` fills (the user cache, `fusion.fetch.cache_dir()`).

    fetch_now: download it into the cache first (`fusion.fetch.fetch`: network, verified); the
        notebook never downloads unasked. Not found and not fetched: with `$FUSION_DATA` set, an
        error (as `load_recording`); else `sim`, said out loud, with the command that fetches it.
    Prints one line naming what was loaded and from where.
    """
    if fetch_now:
        from fusion.fetch import fetch

        report = fetch(name)
        print(report.summary())
        if not report.ok:
            raise RuntimeError(f"fetching {name!r} failed: {report.errors()}")
    try:
        (source,) = datasets.select(name)[:1]
    except ValueError as exc:
        if os.environ.get("FUSION_DATA"):
            raise FileNotFoundError(f"FUSION_DATA={os.environ['FUSION_DATA']} is set, but {exc}") from None
        print(f"NOTE: no recording {name!r} fetched yet (run `fusion data fetch '{name}'`, or set FETCH = True): "
              f"this section runs on '{SIM}', the built-in simulated recording.")
        return datasets.load(SIM)
    recording = datasets.load_source(source)
    print(f"{recording.id}: {len(recording.imu)} IMU samples from {source.imu}")
    return recording


def course_recordings(limit: int | None = None) -> list[str]:
    """Ids of the course recordings with ground truth (`ece276a/1`, ...), or `["sim"]` without data.

    Raises like `load_recording` when `$FUSION_DATA` is set but holds none.
    """
    root = datasets.data_dir_from(None)
    ids = [s.id for s in datasets.select("all", root) if s.kind == "course" and s.vicon is not None]
    if not ids:
        if os.environ.get("FUSION_DATA"):
            raise FileNotFoundError(f"FUSION_DATA={os.environ['FUSION_DATA']} is set, but it holds no course "
                                    "recording with VICON")
        print(f"NOTE: no course recordings under {root.resolve()}: using '{SIM}' instead")
        return [SIM]
    return ids[:limit] if limit else ids


def first_seconds(imu: ImuSamples, seconds: float) -> ImuSamples:
    """The samples of the first `seconds` of a recording (all of them if it is shorter)."""
    stop = int(np.searchsorted(imu.t, imu.t[0] + seconds, side="right"))
    if stop >= len(imu):
        return imu
    print(f"trimmed to the first {seconds:g} s: {stop} of {len(imu)} samples")
    return imu.window(0, stop)
