"""The former name of `fusion.format_checks` (what every file format shares: safe readers,
resource bounds, time-stamp repairs and plausibility checks), kept for one release: importing it
warns and gives that module itself."""
import sys
import warnings

from . import format_checks

warnings.warn("fusion.loaders is now fusion.format_checks (it holds the checks every file format shares, not "
              "loaders); the old name will be removed in the next release", DeprecationWarning, stacklevel=2)
sys.modules[__name__] = format_checks
