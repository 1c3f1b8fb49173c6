"""The built-in simulated recording `sim` (`fusion.sim`): raw counts of the course board with
exact ground truth, calibrated like a course file. It is not a file: never found in a folder,
always available by its id."""
from __future__ import annotations

from collections.abc import Iterator, Sequence
from pathlib import Path

from ..sim import SimSettings, simulate
from ..types import Recording
from .base import Format, Holds, ReadOptions, Source
from .course import calibrated_recording

SIM_ID = "sim"


class SimFormat(Format):
    kind = "sim"
    describe = "the simulated recording `sim`"

    def find(self, root: Path | None, paths: Sequence[Path]) -> Iterator[Source]:
        return iter(())  # `fusion.datasets.discover` lists `sim` with every folder

    def read(self, source: Source, options: ReadOptions) -> Recording:
        # The simulated hardware is the nominal board (with the sim's own sensitivity errors);
        # `options.board` is the user's model of it, used only to calibrate, as for a real file.
        raw, truth = simulate()
        return calibrated_recording(SIM_ID, raw, truth, options.board, options.dropouts)

    def holds(self, source: Source) -> Holds:
        return Holds(truth=True, movement=False, magnetometer=False, gyr_timing=SimSettings().gyr_timing,
                     raw_counts=True)


FORMAT = SimFormat()
