"""Shared fixtures: location of ../shared (real data, reference checkpoints), skipped when absent."""

from pathlib import Path

import pytest

SHARED = Path(__file__).resolve().parents[2] / "shared"
REAL_SUBMAPS = SHARED / "data" / "real" / "submaps"
REFERENCE = SHARED / "reference" / "depoco"


@pytest.fixture
def reference_dir():
    """Folder of the reference checkpoints (e0..e3, golden/); skips the test when ../shared is absent."""
    if not (REFERENCE / "e0" / "enc_best.pth").is_file():
        pytest.skip("reference checkpoints not available (../shared/reference/depoco)")
    return REFERENCE


@pytest.fixture
def real_submaps():
    if not REAL_SUBMAPS.is_dir():
        pytest.skip("real submaps not available (../shared/data/real/submaps)")
    return REAL_SUBMAPS


@pytest.fixture
def run_cli(monkeypatch, capsys):
    """Run the `mapsqueeze` entry point in-process: run_cli(*args) -> (exit code, stdout, stderr)."""
    import sys

    from mapsqueeze.cli import main

    def run(*args: str) -> tuple[int, str, str]:
        monkeypatch.setattr(sys, "argv", ["mapsqueeze", *args])
        with pytest.raises(SystemExit) as exit_info:
            main()
        captured = capsys.readouterr()
        return exit_info.value.code, captured.out, captured.err

    return run
