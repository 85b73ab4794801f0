"""benchmarks/retrain.sh: the one-command retraining of the shipped rate points (simulate, train, pack)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tarfile
from pathlib import Path

import pytest

SCRIPT = Path(__file__).resolve().parents[1] / "benchmarks" / "retrain.sh"


def _run(out: Path, **env: str) -> subprocess.CompletedProcess:
    return subprocess.run(["bash", str(SCRIPT), str(out), "0.5"], capture_output=True, text=True, timeout=300,
                          env={**os.environ, "PYTHON": sys.executable, "WORKERS": "1", **env})


@pytest.mark.slow
def test_retrain_simulates_trains_and_packs_a_model_that_loads(tmp_path):
    from mapsqueeze.model import load_network

    run = _run(tmp_path / "run", DEVICE="cpu", RATES="e1", SUBMAPS="2", SPARSE="1", MAX_STEPS="1")
    assert run.returncode == 0, run.stdout + run.stderr
    assert "e1: 1 steps" in run.stdout
    summary = json.loads((tmp_path / "run" / "e1" / "summary.json").read_text())
    assert summary["steps"] == 1
    assert sorted(path.name for path in (tmp_path / "run").glob("models.tar*")) == ["models.tar"]  # renamed whole
    with tarfile.open(tmp_path / "run" / "models.tar") as tar:
        assert sorted(tar.getnames()) == ["e1", "e1/config.json", "e1/model.safetensors"]
        tar.extractall(tmp_path / "models", filter="data")
    network, _ = load_network(tmp_path / "models" / "e1")
    assert network.config.subsampling_dist == pytest.approx(2.0)
    shipped = SCRIPT.parents[1] / "src" / "mapsqueeze" / "models" / "e1" / "model.safetensors"
    assert (tmp_path / "models" / "e1" / "model.safetensors").read_bytes() != shipped.read_bytes()  # it trained


@pytest.mark.parametrize("device, message", [("cuda", "device 'cuda' is not available"),
                                             ("cuda:7", "device 'cuda:7' is not available"),
                                             ("gpu", "unknown device 'gpu'")])
def test_retrain_refuses_a_device_train_would_refuse_before_simulating(tmp_path, device, message):
    """The check train makes (`devices.torch_device`), once, before minutes of simulation; no OUT folder left."""
    import torch

    if torch.cuda.is_available():
        pytest.skip("a CUDA device is present")
    run = _run(tmp_path / "run", DEVICE=device)
    lines = run.stderr.strip().splitlines()
    assert run.returncode != 0 and len(lines) == 1, run.stderr
    assert lines[0].startswith(f"error: {message}") and lines[0].endswith("; DEVICE=cpu trains on the CPU")
    assert not (tmp_path / "run").exists()
