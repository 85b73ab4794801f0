"""The resolver of the shared material (mapsqueeze.shared) and the rule that CI fails, not skips, without it."""

import os
import subprocess
import sys
from pathlib import Path

import pytest

from mapsqueeze import shared

REPOSITORY = Path(__file__).resolve().parents[1]


def test_environment_overrides_the_shared_folder(tmp_path, monkeypatch):
    monkeypatch.setenv(shared.SHARED_ENV, str(tmp_path))
    assert shared.shared_dir() == tmp_path
    assert shared.real_submaps_dir() == tmp_path / "data" / "real" / "submaps"
    assert shared.reference_checkpoints_dir() == tmp_path / "reference" / "depoco"


def test_default_is_beside_the_source_checkout_else_beside_the_working_directory(tmp_path, monkeypatch):
    monkeypatch.delenv(shared.SHARED_ENV, raising=False)
    monkeypatch.chdir(tmp_path)
    beside_checkout = REPOSITORY.parent / "shared"
    expected = beside_checkout if beside_checkout.is_dir() else tmp_path.parent / "shared"
    assert shared.shared_dir() == expected


def write_executable(path: Path) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("#!/bin/sh\n")
    path.chmod(0o755)
    return path


def test_tmc3_lookup_order_environment_then_path_then_shared_copy(tmp_path, monkeypatch):
    shared_copy = write_executable(tmp_path / "shared" / "tools" / "tmc3" / "tmc3")
    on_path = write_executable(tmp_path / "bin" / "tmc3")
    monkeypatch.setenv(shared.SHARED_ENV, str(tmp_path / "shared"))
    monkeypatch.setenv("PATH", str(tmp_path / "bin"))
    monkeypatch.setenv(shared.TMC3_ENV, "/opt/g-pcc/tmc3")
    assert shared.tmc3_executable() == "/opt/g-pcc/tmc3"
    monkeypatch.delenv(shared.TMC3_ENV)
    assert shared.tmc3_executable() == str(on_path)
    monkeypatch.setenv("PATH", str(tmp_path / "empty"))
    assert shared.tmc3_executable() == str(shared_copy)
    monkeypatch.setenv(shared.SHARED_ENV, str(tmp_path / "nowhere"))
    assert shared.tmc3_executable() is None


def run_reference_test(empty_shared: Path, require: bool) -> subprocess.CompletedProcess:
    env = {**os.environ, shared.SHARED_ENV: str(empty_shared), "MAPSQUEEZE_REQUIRE_SHARED": "1" if require else "0"}
    test = "tests/test_model.py::test_reference_decoder_and_encoder_reproduce_golden[e0]"
    return subprocess.run([sys.executable, "-m", "pytest", test, "-p", "no:cacheprovider", "-rfs"], cwd=REPOSITORY,
                          env=env, capture_output=True, text=True, timeout=300)


@pytest.mark.slow
def test_reference_tests_fail_without_shared_material_when_required(tmp_path):
    required = run_reference_test(tmp_path, require=True)
    assert required.returncode == 1, required.stdout + required.stderr
    assert "1 error" in required.stdout and "MAPSQUEEZE_REQUIRE_SHARED=1 requires it" in required.stdout
    optional = run_reference_test(tmp_path, require=False)
    assert optional.returncode == 0, optional.stdout + optional.stderr
    assert "1 skipped" in optional.stdout
