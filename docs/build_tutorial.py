"""Build the tutorial: turn docs/tutorial/NN_*.py into executed notebooks (and HTML).

The sources are jupytext "percent" scripts (readable diffs); the notebooks are build outputs:

    python docs/build_tutorial.py                       # every notebook -> docs/tutorial/NN_*.ipynb
    python docs/build_tutorial.py --html site/tutorial  # ... and an HTML copy with an index page
    python docs/build_tutorial.py --only 03 --data-dir ../shared/data

Each notebook runs top to bottom in a fresh kernel started with *this* Python
(`sys.executable`), so it imports the `fusion` this interpreter imports (check the first line
every notebook prints), with docs/tutorial as its working directory. `--data-dir` sets
`$FUSION_DATA` for the kernels; without it they see the environment's. A notebook that raises,
or runs longer than `--timeout` seconds in total, fails the build (exit status 1). The run time
of each notebook is printed (and returned by `build`, which `tests/test_tutorial.py` calls).
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

HERE = Path(__file__).resolve().parent
TUTORIAL = HERE / "tutorial"
KERNEL_NAME = "fusion-tutorial"
DEFAULT_TIMEOUT_S = 120.0


@dataclass
class Built:
    """One executed notebook: its source, the written .ipynb, the wall time, the error (None: ran)."""

    source: Path
    notebook: Path | None
    seconds: float
    error: str | None = None
    nb: object = None  # the executed nbformat notebook


def sources(only: list[str] | None = None) -> list[Path]:
    """The notebook sources, in order (`NN_name.py`); `only`: prefixes or names to keep."""
    found = sorted(p for p in TUTORIAL.glob("[0-9][0-9]_*.py"))
    if only:
        found = [p for p in found if any(p.name.startswith(o) or p.stem == o for o in only)]
    return found


def _kernel_dir() -> Path:
    """A Jupyter data folder holding one kernel spec that runs this very interpreter."""
    root = Path(tempfile.mkdtemp(prefix="fusion-tutorial-kernel-"))
    spec = root / "kernels" / KERNEL_NAME
    spec.mkdir(parents=True)
    (spec / "kernel.json").write_text(json.dumps({
        "argv": [sys.executable, "-m", "ipykernel_launcher", "-f", "{connection_file}"],
        "display_name": f"Python ({sys.executable})",
        "language": "python",
        "env": {"MPLBACKEND": "module://matplotlib_inline.backend_inline"},
    }))
    return root


def execute(source: Path, timeout_s: float = DEFAULT_TIMEOUT_S, data_dir: str | None = None,
            out_dir: Path | None = None) -> Built:
    """Convert one source to a notebook, run it, write it to `out_dir` (default: beside the source)."""
    import jupytext
    import nbformat
    from jupyter_client.kernelspec import KernelSpecManager
    from jupyter_client.manager import KernelManager
    from nbclient import NotebookClient
    from nbclient.exceptions import CellExecutionError, CellTimeoutError, DeadKernelError

    nb = jupytext.read(source)
    nb.metadata["kernelspec"] = {"name": "python3", "display_name": "Python 3", "language": "python"}
    nb.metadata.pop("jupytext", None)
    kernel_root = _kernel_dir()
    km = KernelManager(kernel_name=KERNEL_NAME,
                       kernel_spec_manager=KernelSpecManager(kernel_dirs=[str(kernel_root / "kernels")]))
    env = dict(os.environ)
    if data_dir is not None:
        env["FUSION_DATA"] = str(Path(data_dir).resolve())
    deadline = time.monotonic() + timeout_s

    def remaining(cell) -> int:
        return max(1, int(deadline - time.monotonic()) + 1)

    client = NotebookClient(nb, km=km, timeout=int(timeout_s), timeout_func=remaining, allow_errors=False,
                            record_timing=True, resources={"metadata": {"path": str(TUTORIAL)}})
    error = None
    start = time.monotonic()
    try:
        client.execute(env=env)
    except CellTimeoutError:
        error = f"{source.name}: longer than the {timeout_s:.0f} s limit"
    except (CellExecutionError, DeadKernelError) as exc:
        error = f"{source.name}: {exc}"
    finally:
        seconds = time.monotonic() - start
        shutil.rmtree(kernel_root)
    if error is None and seconds > timeout_s:
        error = f"{source.name}: ran {seconds:.0f} s, longer than the {timeout_s:.0f} s limit"
    nb.metadata["kernelspec"] = {"name": "python3", "display_name": "Python 3", "language": "python"}
    target = (out_dir or source.parent) / f"{source.stem}.ipynb"
    target.parent.mkdir(parents=True, exist_ok=True)
    nbformat.write(nb, target)
    return Built(source, target, seconds, error, nb)


def write_html(built: list[Built], html_dir: Path) -> list[Path]:
    """One HTML page per notebook (nbconvert, outputs and figures embedded) and an index.html."""
    from jupyter_core.paths import jupyter_path
    from nbconvert import HTMLExporter

    # nbconvert's templates are data files under <prefix>/share/jupyter. In a virtual environment
    # that sees a base interpreter's packages (--system-site-packages), nbconvert may come from the
    # base, its templates too: add the base prefix to the search path when they are not found.
    if not any((Path(d) / "nbconvert" / "templates" / "lab").is_dir() for d in jupyter_path()):
        base = Path(sys.base_prefix) / "share" / "jupyter"
        if (base / "nbconvert" / "templates" / "lab").is_dir():
            os.environ["JUPYTER_PATH"] = os.pathsep.join(filter(None, [os.environ.get("JUPYTER_PATH"), str(base)]))
    html_dir.mkdir(parents=True, exist_ok=True)
    exporter = HTMLExporter()
    pages = []
    for b in built:
        body, _ = exporter.from_notebook_node(b.nb)
        page = html_dir / f"{b.source.stem}.html"
        page.write_text(body, encoding="utf-8")
        pages.append(page)
    items = "\n".join(f'<li><a href="{p.name}">{_title(b.nb) or p.stem}</a></li>' for b, p in zip(built, pages))
    index = html_dir / "index.html"
    index.write_text("<!DOCTYPE html>\n<html><head><meta charset=\"utf-8\"><title>fusion tutorial</title></head>\n"
                     f"<body><h1>fusion tutorial</h1>\n<ol>\n{items}\n</ol></body></html>\n", encoding="utf-8")
    return [index, *pages]


def _title(nb) -> str:
    """The first Markdown heading of a notebook."""
    for cell in nb.cells:
        if cell.cell_type == "markdown":
            for line in cell.source.splitlines():
                if line.startswith("#"):
                    return line.lstrip("#").strip()
    return ""


def build(only: list[str] | None = None, timeout_s: float = DEFAULT_TIMEOUT_S, data_dir: str | None = None,
          out_dir: Path | None = None, html_dir: Path | None = None, echo=print) -> list[Built]:
    """Execute the selected notebooks in order; print one line per notebook; optionally write HTML."""
    chosen = sources(only)
    if not chosen:
        raise ValueError(f"no notebook source matches {only!r} in {TUTORIAL}")
    built = []
    for source in chosen:
        b = execute(source, timeout_s, data_dir, out_dir)
        echo(f"{source.name:<28} {b.seconds:6.1f} s  {'ok' if b.error is None else 'FAILED'}  -> {b.notebook}")
        built.append(b)
    if html_dir is not None:
        pages = write_html(built, Path(html_dir))
        echo(f"HTML: {pages[0]}")
    return built


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--only", nargs="*", help="notebook prefixes or names to build (default: all)")
    parser.add_argument("--data-dir", help="data directory for the notebooks (sets FUSION_DATA for their kernels)")
    parser.add_argument("--out", type=Path, help="folder for the executed .ipynb (default: docs/tutorial)")
    parser.add_argument("--html", type=Path, metavar="OUTDIR", help="also write an HTML copy (and index.html) there")
    parser.add_argument("--timeout", type=float, default=DEFAULT_TIMEOUT_S, help="seconds per notebook (default 120)")
    args = parser.parse_args(argv)
    built = build(args.only, args.timeout, args.data_dir, args.out, args.html)
    failed = [b for b in built if b.error]
    for b in failed:
        print(f"\n{b.error}", file=sys.stderr)
    total = sum(b.seconds for b in built)
    print(f"{len(built) - len(failed)} of {len(built)} notebooks ran, {total:.0f} s in total")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
