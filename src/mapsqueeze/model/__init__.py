"""The DEPOCO autoencoder: config, weights I/O, the numpy-level CompressionModel and its torch network.

Every name is imported on first use: loading a model and encoding or decoding on the CPU import numpy and numba
but no torch (`inference`); the torch names (the network, saving, the reference import) import torch.
"""

import importlib

_MODULE_OF = {
    "CompressionModel": "compression", "Embedding": "compression",
    "RATE_SUBSAMPLING_M": "config", "ModelConfig": "config", "density_law": "config", "density_law_factors": "config",
    "load_model": "shipped", "shipped_models": "shipped",
    "Autoencoder": "autoencoder", "import_reference": "checkpoint", "load_network": "checkpoint",
    "save_model": "checkpoint",
}


def __getattr__(name: str):
    if name in _MODULE_OF:
        return getattr(importlib.import_module(f"mapsqueeze.model.{_MODULE_OF[name]}"), name)
    raise AttributeError(f"module 'mapsqueeze.model' has no attribute {name!r}")


def build_model(config, seed: int = 0):
    """A freshly initialised torch `Autoencoder` of a `ModelConfig` (deterministic for a given seed)."""
    import torch

    from mapsqueeze.model.autoencoder import Autoencoder

    torch.manual_seed(seed)
    return Autoencoder(config)


__all__ = [*_MODULE_OF, "build_model"]
