"""fusion: orientation from a gyroscope and an accelerometer, scored against motion capture."""
__version__ = "0.1.0"


def check_package_name(name: str, package: str) -> None:
    """Refuse a folder of the project imported under its folder's name (`import estimators` from
    the project's root) instead of the package it is installed as: a second copy would have its
    own registries, and its compiled kernels would write types into numba's disk cache under a
    name that other processes cannot import."""
    if name != package:
        raise ImportError(f"{name}: this folder is the package {package}; import {package} instead")
