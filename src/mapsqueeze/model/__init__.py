"""The DEPOCO autoencoder: config, weights I/O, the numpy-level CompressionModel and its torch network.

Importing this package, loading a model and encoding or decoding on the CPU import no torch (`inference`); the
torch names below (the network, training, saving, the reference import) import it when first used.
"""

from mapsqueeze.model.compression import CompressionModel, Embedding
from mapsqueeze.model.config import RATE_SUBSAMPLING_M, ModelConfig, density_law, density_law_factors
from mapsqueeze.model.store import load_model, shipped_models

_TORCH_NAMES = {"Autoencoder": "autoencoder", "import_reference": "checkpoint", "load_network": "checkpoint",
                "save_model": "checkpoint"}


def __getattr__(name: str):
    """The torch names, imported on first use."""
    if name in _TORCH_NAMES:
        import importlib

        return getattr(importlib.import_module(f"mapsqueeze.model.{_TORCH_NAMES[name]}"), name)
    raise AttributeError(f"module 'mapsqueeze.model' has no attribute {name!r}")


def build_model(config: ModelConfig, seed: int = 0):
    """A freshly initialised torch `Autoencoder` (deterministic for a given seed)."""
    import torch

    from mapsqueeze.model.autoencoder import Autoencoder

    torch.manual_seed(seed)
    return Autoencoder(config)


__all__ = [
    "Autoencoder", "CompressionModel", "Embedding", "ModelConfig", "RATE_SUBSAMPLING_M", "build_model",
    "density_law", "density_law_factors", "import_reference", "load_model", "load_network",
    "save_model", "shipped_models",
]
