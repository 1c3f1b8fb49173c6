"""The rules for skipping (tests/optional_helpers.py): a missing optional thing skips a test on a
developer's machine and fails it under CI (`CI=true`, which `.ci/run` exports); a data folder
named but empty always fails; and only a peer's construction is guarded, never its run."""
from __future__ import annotations

import re
from pathlib import Path

import pytest

import fusion.estimators.peers.vqf_fusion as peers
from fusion import estimators
from fusion.estimators.dr import DeadReckoning

import optional_helpers
from optional_helpers import build_estimator, build_if_available, optional_module, real_data_dir, require_module

CI_SCRIPT = Path(__file__).resolve().parents[1] / ".ci" / "run"


@pytest.fixture
def no_peer_libraries(monkeypatch):
    """Every peer's library import fails, as on a machine without `.[peers]`."""
    def refuse(name, *args, **kwargs):
        raise ModuleNotFoundError(f"No module named {name!r}")

    monkeypatch.setattr(peers.importlib, "import_module", refuse)


@pytest.fixture(params=[False, True], ids=["local", "ci"])
def ci(request, monkeypatch) -> bool:
    if request.param:
        monkeypatch.setenv("CI", "true")
    else:
        monkeypatch.delenv("CI", raising=False)
    return request.param


def outcome(ci: bool) -> type[BaseException]:
    return pytest.fail.Exception if ci else pytest.skip.Exception


def test_ci_script_declares_ci_before_running_the_tests():
    lines = CI_SCRIPT.read_text().splitlines()
    exports = [i for i, line in enumerate(lines) if re.fullmatch(r"export CI=true", line.strip())]
    runs = [i for i, line in enumerate(lines) if "pytest" in line and not line.lstrip().startswith("#")]
    assert exports and runs and exports[0] < runs[-1], "`.ci/run` must export CI=true before it runs pytest"
    assert any(line.startswith("export FUSION_DATA=") for line in lines)


def test_ci_installs_qmt_from_source_with_the_test_extra():
    """qmt's only wheel does not import under NumPy 2: the test extra holds qmt, and `.ci/run`
    installs that extra with `PIP_NO_BINARY=qmt` (its source distribution, built against NumPy 2),
    so that the qmt peers' tests run under CI (where a missing qmt fails them)."""
    import configparser

    config = configparser.ConfigParser()
    config.read(CI_SCRIPT.parents[1] / "setup.cfg")
    test_extra = [line.strip() for line in config["options.extras_require"]["test"].splitlines()]
    assert any(line.startswith("qmt") for line in test_extra), test_extra
    installs = [line for line in CI_SCRIPT.read_text().splitlines()
                if "pip install" in line and "[test]" in line and not line.lstrip().startswith("#")]
    assert installs and all(line.strip().startswith("PIP_NO_BINARY=qmt ") for line in installs), installs


def test_unset_data_variable_skips_locally_and_fails_under_ci(ci, monkeypatch):
    monkeypatch.delenv("FUSION_DATA", raising=False)
    with pytest.raises(outcome(ci), match="FUSION_DATA is not set"):
        real_data_dir()


def test_data_variable_naming_an_empty_folder_always_fails(ci, monkeypatch, tmp_path):
    monkeypatch.setenv("FUSION_DATA", str(tmp_path))
    with pytest.raises(pytest.fail.Exception, match=r"is set but holds no ece276a/imu/imuRaw1\.p"):
        real_data_dir()


def test_data_variable_naming_the_recordings_gives_their_folder(monkeypatch, tmp_path):
    (tmp_path / optional_helpers.COURSE_FILE).parent.mkdir(parents=True)
    (tmp_path / optional_helpers.COURSE_FILE).write_bytes(b"")
    monkeypatch.setenv("FUSION_DATA", str(tmp_path))
    assert real_data_dir() == tmp_path.resolve()


def test_missing_peer_library_skips_locally_and_fails_under_ci(ci, no_peer_libraries):
    with pytest.raises(outcome(ci), match=r"'vqf' needs the optional package 'vqf'"):
        build_estimator("vqf")
    if ci:
        with pytest.raises(pytest.fail.Exception, match="pip install"):
            build_if_available("mahony")
    else:
        assert build_if_available("mahony") is None
    assert isinstance(build_estimator("dr"), DeadReckoning)  # our own estimators need nothing optional


def test_other_import_errors_while_building_are_not_caught(monkeypatch):
    class Broken(DeadReckoning):
        def __init__(self, params=None):
            raise ImportError("a broken dependency, not an optional peer")

    monkeypatch.setitem(estimators.ESTIMATORS, "dr", Broken)
    for build in (build_estimator, build_if_available):
        with pytest.raises(ImportError, match="a broken dependency") as err:
            build("dr")
        assert not isinstance(err.value, peers.PeerUnavailable)


def test_missing_optional_module_skips_locally_and_fails_under_ci(ci):
    name = "fusion_no_such_module"
    if ci:
        with pytest.raises(pytest.fail.Exception, match=name):
            optional_module(name)
    else:
        assert optional_module(name) is None
    with pytest.raises(outcome(ci), match=name):
        require_module(name)
    assert require_module("scipy.io").__name__ == "scipy.io"
