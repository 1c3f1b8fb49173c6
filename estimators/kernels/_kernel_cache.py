"""Keeping numba's on-disk cache of the compiled kernels honest about the files they call into.

numba keys a cached function on its own source file alone (its modification time and size): a
kernel that calls a function of another module (`fusion.quaternion`'s scalar path, compiled
where the kernel is) is not recompiled when only that module changes, and would run the old code.
`forget_stale_kernels` closes that gap for the in-tree cache (`__pycache__` beside the kernel
module, where numba caches an installed or editable package): it keeps a stamp of the
dependencies' contents there and, when it differs, deletes that module's cache files before
numba reads them, so that they are compiled afresh. A cache elsewhere (`NUMBA_CACHE_DIR`, or
numba's per-user folder when `__pycache__` is not writable) belongs to an installation whose
files do not change in place.
"""
from __future__ import annotations

import hashlib
from pathlib import Path


def forget_stale_kernels(module_file: str, dependencies: list[str]) -> None:
    """Delete the in-tree numba cache of the module at `module_file` when any file of
    `dependencies` changed since the cache was written (a stamp of their sha256 is kept beside it)."""
    module = Path(module_file)
    cache = module.parent / "__pycache__"
    digest = hashlib.sha256()
    for path in dependencies:
        digest.update(Path(path).read_bytes())
    stamp = cache / f"{module.stem}.dependencies.sha256"
    try:
        if stamp.exists():
            if stamp.read_text() == digest.hexdigest():
                return
            for pattern in (f"{module.stem}.*.nbi", f"{module.stem}.*.nbc"):
                for path in cache.glob(pattern):
                    path.unlink(missing_ok=True)
        # No stamp: a new installation (nothing cached yet), or a cache written before stamps were
        # kept, whose kernels numba dates by their own file; from now on the stamp decides.
        cache.mkdir(exist_ok=True)
        stamp.write_text(digest.hexdigest())
    except OSError:  # a read-only installation: nothing there changes in place
        pass
