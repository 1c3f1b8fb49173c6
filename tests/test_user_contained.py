"""A user's estimator that ends its process by mistake (`sys.exit`, `raise SystemExit`, `raise
KeyboardInterrupt`, `os._exit`, a segfault in code it calls) costs its own row, one line naming
it; the other rows, the table and the results file stay, the command exits 1. A real Ctrl-C still
stops the run, with the hint to resume it."""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time

import pytest

from fusion import datasets
from fusion.cli import main
from fusion.estimators import resolve
from fusion.evaluation.run.job import run_one
from fusion.evaluation.run.pool import death_text

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="forks workers and sends signals")

STOPS = '''
import ctypes
import os
import signal
import sys
import time
from pathlib import Path


def exits(t, gyro, acc, q0):
    sys.exit(0)


def system_exit(t, gyro, acc, q0):
    raise SystemExit("done")


def interrupts(t, gyro, acc, q0):
    raise KeyboardInterrupt


def hard_exit(t, gyro, acc, q0):
    os._exit(0)


def segfault(t, gyro, acc, q0):
    ctypes.string_at(0)  # reads address 0: SIGSEGV


def real_ctrl_c(t, gyro, acc, q0):
    os.kill(os.getpid(), signal.SIGINT)  # as the terminal's Ctrl-C: a real signal to this process
    time.sleep(5)


def waits(t, gyro, acc, q0):
    Path(os.environ["STARTED"]).write_text("started")
    time.sleep(60)
'''

# the line each stop is on in STOPS (1-based), for the error's "at stops.py:LINE"
LINES = {name: next(i for i, line in enumerate(STOPS.splitlines(), 1) if line.startswith(f"def {name}(")) + 1
         for name in ("exits", "system_exit", "interrupts")}

EXPECTED = {
    "stops.exits": f"raised SystemExit(0) (what sys.exit does) at stops.py:{LINES['exits']} in exits: an estimator "
                   "returns its orientations or raises an exception, it does not end the process",
    "stops.system_exit": f"raised SystemExit('done') (what sys.exit does) at stops.py:{LINES['system_exit']}",
    "stops.interrupts": f"raised KeyboardInterrupt at stops.py:{LINES['interrupts']} in interrupts (its own code, not a "
                        "Ctrl-C)",
    "stops.hard_exit": "the worker process running it exited with status 0 (os._exit",
    "stops.segfault": "killed by signal 11 (SIGSEGV: a crash in compiled code it ran",
}


@pytest.fixture
def folder(tmp_path, monkeypatch):
    monkeypatch.delenv("FUSION_DATA", raising=False)
    (tmp_path / "stops.py").write_text(STOPS)
    monkeypatch.chdir(tmp_path)
    return tmp_path


def specs(*names: str) -> str:
    return ",".join(f"./stops.py:{name}" for name in names)


@pytest.mark.slow
@pytest.mark.parametrize("jobs", ["1", "2"])
def test_every_way_of_ending_the_process_costs_its_row_only(folder, capfd, jobs):
    """capfd: the workers' stderr too (file descriptor 2, which they inherit), so that a crash's own
    output would show: the segfaulting worker prints nothing, its parent one line."""
    code = main(["compare", "--estimators", specs(*(label.split(".")[1] for label in EXPECTED)) + ",dr",
                 "--dataset", "sim", "--no-progress", "--jobs", jobs, "--json", "r.json"])
    out, err = capfd.readouterr()
    assert code == 1
    assert "Fatal Python error" not in err and "Traceback" not in err, err
    errors = [line for line in err.splitlines() if line.startswith("fusion: error: ")]
    assert len(errors) == len(EXPECTED), errors
    assert all(line.startswith(("fusion: error: ", "fusion: warning: ")) for line in err.splitlines()), err
    for label, message in EXPECTED.items():
        (line,) = [e for e in errors if f"'{label}'" in e]
        assert line.startswith("fusion: error: sim: estimator") and message in line, line
    rows = {r["estimator"]: r for r in json.loads((folder / "r.json").read_text())["results"]}
    assert "error" not in rows["dr"] and rows["dr"]["rmse_deg"]["total"] > 0
    assert all(rows[label]["rmse_deg"] is None and rows[label]["error"] for label in EXPECTED)
    assert f"failed (no result; the errors say why): {len(EXPECTED)} rows" in out
    assert next(line for line in out.splitlines() if line.startswith("sim ") and " dr " in line).split()[2] != "failed"


@pytest.mark.slow
def test_the_command_line_keeps_the_table_and_the_folder(folder):
    """`python -m fusion`: exit status 1 (not the 0 of sys.exit(0)), the table printed, results.json
    and the report written, with --jobs 1."""
    env = dict(os.environ, MPLBACKEND="Agg")
    proc = subprocess.run([sys.executable, "-m", "fusion", "compare", "--estimators", specs("exits", "hard_exit") + ",dr",
                           "--dataset", "sim", "--no-progress", "--jobs", "1", "--out", "run"], cwd=folder, env=env,
                          capture_output=True, text=True, timeout=600)
    assert proc.returncode == 1, proc.stderr
    assert "failed (no result; the errors say why): 2 rows" in proc.stdout
    rows = {r["estimator"]: r for r in json.loads((folder / "run" / "results.json").read_text())["results"]}
    assert rows["dr"]["rmse_deg"]["total"] > 0 and "SystemExit(0)" in rows["stops.exits"]["error"]
    assert (folder / "run" / "report.html").is_file()


@pytest.fixture
def ctrl_c():
    """Ctrl-C as a terminal delivers it, whatever started the tests: a shell that runs them in the
    background leaves SIGINT ignored, which this process and the commands it starts would inherit."""
    before = signal.signal(signal.SIGINT, signal.default_int_handler)
    yield
    signal.signal(signal.SIGINT, before)


def test_a_real_ctrl_c_in_the_estimator_still_stops(folder, ctrl_c):
    """In this process (run_one, as `fusion panorama` runs it): a KeyboardInterrupt the code raises
    is its row's error; a real SIGINT delivered while it runs stops the caller."""
    rec = datasets.load("sim")
    with pytest.raises(ValueError, match=r"raised KeyboardInterrupt at stops.py:\d+ in interrupts"):
        run_one(rec, resolve("./stops.py:interrupts"))
    with pytest.raises(ValueError, match=r"raised SystemExit\(0\) \(what sys.exit does\)"):
        run_one(rec, resolve("./stops.py:exits"))
    with pytest.raises(KeyboardInterrupt):
        run_one(rec, resolve("./stops.py:real_ctrl_c"))
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler  # put back as it was


@pytest.mark.slow
def test_ctrl_c_on_the_terminal_stops_the_run_with_the_resume_hint(folder, ctrl_c):
    """The user's Ctrl-C (SIGINT to the command's process group) while a user's estimator runs in its
    worker: the run stops as before (status 130) and says how to continue it."""
    env = dict(os.environ, MPLBACKEND="Agg", STARTED=str(folder / "started"))
    proc = subprocess.Popen([sys.executable, "-m", "fusion", "compare", "--estimators", specs("waits") + ",dr",
                             "--dataset", "sim", "--no-progress", "--jobs", "1", "--out", "run"], cwd=folder, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True)
    try:
        deadline = time.monotonic() + 300
        while not (folder / "started").exists():
            assert proc.poll() is None and time.monotonic() < deadline, proc.communicate()
            time.sleep(0.1)
        os.killpg(proc.pid, signal.SIGINT)
        out, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 128 + signal.SIGINT, err
    assert "fusion: interrupted; continue with: fusion compare --resume run" in err
    assert not (folder / "run" / "results.json").exists()


def test_how_a_worker_died_is_said():
    assert death_text(0).startswith("the worker process running it exited with status 0 (os._exit")
    assert "signal 11 (SIGSEGV: a crash in compiled code" in death_text(-signal.SIGSEGV)
    assert "signal 9 (SIGKILL: killed from outside: out of memory?)" in death_text(-signal.SIGKILL)
    assert "signal 15 (SIGTERM: killed from outside)" in death_text(-signal.SIGTERM)


def test_a_script_that_exits_on_import_is_one_line(folder, capsys):
    """A file whose own code calls sys.exit when it is imported: one line saying so, status 1."""
    (folder / "script.py").write_text("import sys\n\ndef f(t, gyro, acc, q0):\n    return None\n\nsys.exit(0)\n")
    assert main(["compare", "--estimators", "./script.py:f", "--dataset", "sim", "--no-progress"]) == 1
    (line,) = capsys.readouterr().err.strip().splitlines()
    assert "script.py: running it called sys.exit(0); put the script's own code under" in line
