"""The DEPOCO autoencoder: config, network, weights I/O and the numpy-level CompressionModel."""

from mapsqueeze.model.autoencoder import Autoencoder, CompressionModel, Embedding
from mapsqueeze.model.checkpoint import (
    import_reference,
    load_model,
    load_network,
    save_model,
    shipped_models,
)
from mapsqueeze.model.config import RATE_SUBSAMPLING_M, ModelConfig, density_law, density_law_factors


def build_model(config: ModelConfig, seed: int = 0) -> Autoencoder:
    """A freshly initialised network (deterministic for a given seed)."""
    import torch

    torch.manual_seed(seed)
    return Autoencoder(config)


__all__ = [
    "Autoencoder", "CompressionModel", "Embedding", "ModelConfig", "RATE_SUBSAMPLING_M", "build_model",
    "density_law", "density_law_factors", "import_reference", "load_model", "load_network",
    "save_model", "shipped_models",
]
