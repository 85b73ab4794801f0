"""Models on disk without torch: config.json + model.safetensors (never pickle), the shipped models, loading a
`CompressionModel` (imported then: naming the shipped models needs neither numba nor torch). Writing weights and
building the torch network from them: `checkpoint`."""

from __future__ import annotations

import hashlib
import re
from pathlib import Path

import numpy as np

from mapsqueeze.errors import ModelError
from mapsqueeze.model.config import ModelConfig

WEIGHTS_FILE = "model.safetensors"
CONFIG_FILE = "config.json"
SHIPPED_DIR = Path(__file__).resolve().parents[1] / "models"


def shipped_models() -> list[str]:
    """Names of the models shipped inside the package (e.g. e0..e3)."""
    if not SHIPPED_DIR.is_dir():
        return []
    return sorted(p.name for p in SHIPPED_DIR.iterdir() if (p / WEIGHTS_FILE).is_file())


def shipped_weights_sha256(name: str) -> str | None:
    """SHA-256 (hex) of a shipped model's weights file, or None when no shipped model has that name."""
    if name not in shipped_models():
        return None
    return hashlib.sha256((SHIPPED_DIR / name / WEIGHTS_FILE).read_bytes()).hexdigest()


def resolve_model_dir(name_or_path: str | Path, shipped_only: bool = False) -> Path:
    """A shipped model name (e.g. 'e1') or, unless shipped_only, a directory holding config.json +
    model.safetensors (a directory comes first)."""
    path = Path(name_or_path)
    if not shipped_only and (path / WEIGHTS_FILE).is_file():
        return path
    shipped = SHIPPED_DIR / str(name_or_path)
    if re.fullmatch(r"[A-Za-z0-9_.-]+", str(name_or_path)) and (shipped / WEIGHTS_FILE).is_file():
        return shipped
    available = ", ".join(shipped_models()) or "none shipped"
    if not shipped_only and path.is_dir():
        raise ModelError(f"model folder {str(name_or_path)!r} holds no {WEIGHTS_FILE} (a model folder holds "
                         f"{WEIGHTS_FILE} + {CONFIG_FILE}; shipped models: {available})")
    raise ModelError(f"model {str(name_or_path)!r} not found (a directory with {WEIGHTS_FILE} + {CONFIG_FILE}, "
                     f"or a shipped model: {available})")


def read_weights(model_dir: Path) -> tuple[ModelConfig, dict[str, np.ndarray], str]:
    """(config, tensors by state-dict name, SHA-256 of the weights file) of a model directory."""
    from safetensors import SafetensorError
    from safetensors.numpy import load

    model_dir = Path(model_dir)
    config = ModelConfig.load(model_dir / CONFIG_FILE)
    weights_path = model_dir / WEIGHTS_FILE
    try:
        data = weights_path.read_bytes()
        tensors = load(data)
    except (SafetensorError, OSError, ValueError) as exc:
        raise ModelError(f"cannot load weights {weights_path}: {str(exc).splitlines()[0]}") from None
    return config, tensors, hashlib.sha256(data).hexdigest()


def load_model(name_or_path: str | Path = "e1", device: str = "cpu", shipped_only: bool = False):
    """Load a shipped or saved `CompressionModel` to run on `device` (MapsqueezeError for one this machine lacks,
    `devices.device_name`); shipped_only refuses paths (names read from files). On the CPU this imports no torch."""
    from mapsqueeze.model.compression import CompressionModel
    from mapsqueeze.model.devices import device_name

    device = device_name(device)
    model_dir = resolve_model_dir(name_or_path, shipped_only)
    config, tensors, sha = read_weights(model_dir)
    try:
        return CompressionModel(config, tensors, config.name, sha, device=device)
    except ModelError as exc:
        raise ModelError(f"cannot load weights {model_dir / WEIGHTS_FILE}: {exc}") from None
