"""The BROAD reader, now `fusion.formats.broad`; its names stay importable from here."""
from __future__ import annotations

from .formats.broad import REQUIRED, SUFFIXES, is_trial, load_broad, read_trial

__all__ = ["REQUIRED", "SUFFIXES", "is_trial", "load_broad", "read_trial"]
