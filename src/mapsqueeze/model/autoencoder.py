"""The DEPOCO autoencoder (paper Fig. 2) on torch: training, passes and encode-time refinement on a GPU."""

from __future__ import annotations

import numpy as np
import torch
from torch import nn

from mapsqueeze.geometry.threads import one_torch_thread
from mapsqueeze.model.config import ModelConfig
from mapsqueeze.model.deconv import AdaptiveDeconv
from mapsqueeze.model.kpconv import EncoderBlock


class Encoder(nn.Module):
    """Three KPConv blocks with grid subsampling, then a linear layer to the embedding feature."""

    def __init__(self, config: ModelConfig):
        super().__init__()
        scale = config.map_size
        dims = (1,) + config.encoder_dims
        self.blocks = nn.ModuleList(
            EncoderBlock(dims[i], dims[i + 1], grid / scale, radius / scale, config.max_neighbors[i],
                         config.num_kernel_points, config.leaky_relu_slope, config.batchnorm_momentum)
            for i, (grid, radius) in enumerate(zip(config.block_grid_sizes(), config.block_kernel_radii())))
        self.embedding = nn.Linear(config.encoder_dims[-1], config.embedding_dim)

    def forward(self, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """points (N,3) normalised -> embedding points (M,3) normalised, features (M, embedding_dim)."""
        features = torch.ones(points.shape[0], 1, dtype=points.dtype, device=points.device)  # occupancy
        for block in self.blocks:
            points, features = block(points, features)
        return points, self.embedding(features)


class Decoder(nn.Module):
    """Four adaptive deconvolutions, then a linear layer whose output refines the coordinates."""

    def __init__(self, config: ModelConfig):
        super().__init__()
        dims = [config.embedding_dim] + [config.decoder_dim] * len(config.upsampling_factors)
        self.blocks = nn.ModuleList(
            AdaptiveDeconv(dims[i], dims[i + 1], k, config.decoder_kernel_radius, config.decoder_hidden,
                           config.leaky_relu_slope)
            for i, k in enumerate(config.upsampling_factors))
        self.refine = nn.Linear(config.decoder_dim, 3)

    def forward(self, points: torch.Tensor, features: torch.Tensor) -> tuple[torch.Tensor, list[torch.Tensor]]:
        """Embedding (normalised) -> (output points, [cloud after each deconvolution]) in normalised units."""
        intermediate = []
        for block in self.blocks:
            points, features = block(points, features)
            intermediate.append(points)
        return points + self.refine(features), intermediate


class Autoencoder(nn.Module):
    """Encoder + decoder of one rate point; all coordinates normalised (tile-local metres / map_size)."""

    def __init__(self, config: ModelConfig):
        super().__init__()
        self.config = config
        self.encoder = Encoder(config)
        self.decoder = Decoder(config)

    def forward(self, points: torch.Tensor):
        emb_points, emb_features = self.encoder(points)
        output, intermediate = self.decoder(emb_points, emb_features)
        return output, intermediate, (emb_points, emb_features)


def _to_numpy(*tensors: torch.Tensor) -> tuple[np.ndarray, ...]:
    return tuple(t.detach().cpu().numpy() for t in tensors)


@torch.no_grad()
def torch_encode(network: Autoencoder, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """`Encoder` of points (N, 3) float32 normalised on the network's device -> (embedding points, features) as
    numpy; the same bytes whatever torch's thread count (`one_torch_thread`)."""
    device = next(network.parameters()).device
    with one_torch_thread():
        return _to_numpy(*network.encoder(torch.from_numpy(points).to(device)))


@torch.no_grad()
def torch_decode(network: Autoencoder, points: np.ndarray, features: np.ndarray) -> np.ndarray:
    """`Decoder` output points of an embedding (normalised numpy arrays) on the network's device, as numpy."""
    device = next(network.parameters()).device
    with one_torch_thread():
        output, _ = network.decoder(torch.from_numpy(points).to(device), torch.from_numpy(features).to(device))
    return _to_numpy(output)[0]


def torch_refine(network: Autoencoder, target: np.ndarray, points: np.ndarray, features: np.ndarray,
                 steps: int, dead_zone: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """`refinetorch.refine_embedding_torch` with the network's decoder on its device; numpy arrays in and out,
    normalised (`dead_zone` too)."""
    from mapsqueeze.model.refinetorch import refine_embedding_torch

    device = next(network.parameters()).device
    tensors = (torch.from_numpy(a).to(device) for a in (target, points, features))
    with one_torch_thread():
        return _to_numpy(*refine_embedding_torch(network.decoder, *tensors, steps, dead_zone))
