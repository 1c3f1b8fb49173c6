"""The compiled kernels' cache follows the files they call into (`_kernel_cache`)."""
from __future__ import annotations

from fusion.estimators.kernels._kernel_cache import forget_stale_kernels


def test_cache_dropped_when_a_dependency_changes_and_kept_otherwise(tmp_path):
    module, dependency = tmp_path / "_kernels.py", tmp_path / "quaternion.py"
    module.write_text("# kernels\n")
    dependency.write_text("def f(): return 1\n")
    cache = tmp_path / "__pycache__"
    cache.mkdir()

    def cached(name: str) -> list[str]:
        for suffix in (".nbi", ".1.nbc"):
            (cache / f"_kernels.{name}-10.py311{suffix}").write_text("compiled")
        other = cache / "other.g-3.py311.nbi"  # another module's cache is not touched
        other.write_text("compiled")
        return sorted(p.name for p in cache.iterdir() if not p.name.endswith(".sha256"))

    before = cached("kernel")
    forget_stale_kernels(str(module), [str(dependency)])  # no stamp yet: the stamp is written, nothing dropped
    assert sorted(p.name for p in cache.iterdir()) == sorted(before + ["_kernels.dependencies.sha256"])

    forget_stale_kernels(str(module), [str(dependency)])  # unchanged: kept
    assert (cache / "_kernels.kernel-10.py311.nbi").exists()

    dependency.write_text("def f(): return 2\n")
    forget_stale_kernels(str(module), [str(dependency)])  # changed: dropped
    assert not (cache / "_kernels.kernel-10.py311.nbi").exists() and not (cache / "_kernels.kernel-10.py311.1.nbc").exists()
    assert (cache / "other.g-3.py311.nbi").exists()
