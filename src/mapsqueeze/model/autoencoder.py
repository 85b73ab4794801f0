"""The DEPOCO autoencoder (paper Fig. 2) and the numpy-level model used by the codec."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import nn

from mapsqueeze.errors import ModelError
from mapsqueeze.geometry.resample import resample_to_count
from mapsqueeze.geometry.threads import one_torch_thread
from mapsqueeze.model.config import ModelConfig
from mapsqueeze.model.deconv import AdaptiveDeconv
from mapsqueeze.model.kpconv import EncoderBlock
from mapsqueeze.model.refine import refine_embedding


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


@dataclass
class Embedding:
    """The compressed form of one tile: points (M,3) float32 tile-local metres, features (M,D) float32."""

    points: np.ndarray
    features: np.ndarray


class CompressionModel:
    """A trained autoencoder with a numpy API in tile-local metres (what the codec calls)."""

    def __init__(self, network: Autoencoder, model_id: str, weights_sha256: str, device: str = "cpu"):
        self.network = network.to(device).eval()
        self.config = network.config
        self.model_id = model_id
        self.weights_sha256 = weights_sha256
        self.device = torch.device(device)

    def select_input(self, points_local: np.ndarray) -> np.ndarray:
        """At most config.max_input_points points, drawn with a fixed seed (deterministic encoding)."""
        if len(points_local) <= self.config.max_input_points:
            return points_local
        rng = np.random.default_rng(0)
        keep = np.sort(rng.choice(len(points_local), self.config.max_input_points, replace=False))
        return points_local[keep]

    @torch.no_grad()
    def encode(self, points_local: np.ndarray) -> Embedding:
        """Tile-local points (N,3) metres -> embedding (positions in metres, features). Like `refine` and `decode`,
        the same bytes whatever torch's thread count (`one_torch_thread`)."""
        with one_torch_thread():
            emb_points, emb_features = self.network.encoder(self._normalised_input(points_local))
        return self._embedding(emb_points, emb_features)

    def refine(self, points_local: np.ndarray, embedding: Embedding, steps: int) -> Embedding:
        """The embedding of these tile-local points after `steps` steps of encode-time refinement towards a lower
        D_e of the decoder's output against all of them (not only the encoder's max_input_points; `refine_embedding`:
        same format, ~0.5-1 s a step for a 40 m tile on one core)."""
        points, features = self._normalised_embedding(embedding.points, embedding.features)
        scale = np.float32(self.config.map_size)
        target = torch.from_numpy(np.asarray(points_local, dtype=np.float32) / scale).to(self.device)  # every point
        with one_torch_thread():
            points, features = refine_embedding(self.network.decoder, target, points, features, steps)
        return self._embedding(points, features)

    def _normalised_input(self, points_local: np.ndarray) -> torch.Tensor:
        scale = np.float32(self.config.map_size)
        return torch.from_numpy(np.asarray(self.select_input(points_local), dtype=np.float32) / scale).to(self.device)

    def _normalised_embedding(self, points: np.ndarray, features: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
        scale = np.float32(self.config.map_size)
        return (torch.from_numpy(np.ascontiguousarray(points, dtype=np.float32) / scale).to(self.device),
                torch.from_numpy(np.ascontiguousarray(features, dtype=np.float32)).to(self.device))

    def _embedding(self, points: torch.Tensor, features: torch.Tensor) -> Embedding:
        scale = np.float32(self.config.map_size)
        return Embedding((points.cpu().numpy() * scale).astype(np.float32), features.cpu().numpy().astype(np.float32))

    @torch.no_grad()
    def decode(self, points: np.ndarray, features: np.ndarray, n_points: int | None = None) -> np.ndarray:
        """Embedding -> dense cloud (K,3) float32 tile-local metres.

        n_points=None gives the native count (M x prod(K_i)). A smaller count keeps an evenly spread deterministic
        subset (`resample_to_count`); a larger one adds midpoints between each output point and its nearest
        neighbours (arbitrary density). Raises ModelError if the network outputs a non-finite coordinate.
        """
        scale = np.float32(self.config.map_size)
        p, f = self._normalised_embedding(points, features)
        if len(p) == 0:
            return np.zeros((0, 3), dtype=np.float32)
        with one_torch_thread():
            output, _ = self.network.decoder(p, f)
        cloud = output.cpu().numpy() * scale
        if not np.isfinite(cloud).all():
            raise ModelError(f"model {self.model_id!r} decoded non-finite coordinates (broken weights?)")
        return resample_to_count(cloud, n_points).astype(np.float32)
