"""The evaluation layer of `fusion`: scoring, runs, reports, plots and panoramas."""
from fusion import check_package_name

check_package_name(__name__, "fusion.evaluation")
