"""Encoder: KPConv ResNet-like blocks with grid subsampling (paper Sec. III, eq. 1-2)."""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import nn

from mapsqueeze.geometry.grid import grid_subsample, radius_neighbors
from mapsqueeze.model.influences import cpu_influences
from mapsqueeze.model.kernels import grid_kernel_points, kernel_sigma, query_chunk


class KPConv(nn.Module):
    """Rigid kernel point convolution with linear influence max(0, 1 - d / sigma) (eq. 1-2)."""

    def __init__(self, in_dim: int, out_dim: int, radius: float, num_kernel_points: int = 27):
        super().__init__()
        self.radius = radius
        self.sigma = kernel_sigma(radius, num_kernel_points)  # kernel point influence extent
        self.weights = nn.Parameter(torch.empty(num_kernel_points, in_dim, out_dim))
        nn.init.kaiming_uniform_(self.weights, a=math.sqrt(5))
        self.register_buffer("kernel_points", torch.from_numpy(grid_kernel_points(radius, num_kernel_points)))

    def forward(self, queries: torch.Tensor, source: torch.Tensor, neighbors: torch.Tensor, features: torch.Tensor):
        """queries (Q,3), source (N,3), neighbors (Q,K) indices into source (N = shadow), features (N,C) -> (Q,D).

        Queries are processed in chunks (`kernels.query_chunk`). The influences depend on the point positions only,
        which are inputs (no gradient flows to them); on the CPU a compiled kernel computes them, elsewhere torch.
        """
        padded_features = torch.cat([features, torch.zeros_like(features[:1])], dim=0)
        chunk = query_chunk(neighbors.shape[1], len(self.kernel_points))
        influences = self._cpu_influences if queries.device.type == "cpu" else self._torch_influences
        geometry = (queries.detach(), source.detach(), neighbors)
        weighted = torch.cat([torch.matmul(influences(*geometry, s, min(len(queries), s + chunk)),
                                           padded_features[neighbors[s:s + chunk]])  # (Q, M, C)
                              for s in range(0, max(len(queries), 1), chunk)])
        return weighted.reshape(len(weighted), -1) @ self.weights.reshape(-1, self.weights.shape[2])  # sum over m, c

    def _cpu_influences(self, queries, source, neighbors, first: int, stop: int) -> torch.Tensor:
        """`kernels.cpu_influences` of queries [first, stop) as a tensor."""
        arrays = (np.ascontiguousarray(t.numpy()) for t in (queries, source, neighbors, self.kernel_points))
        return torch.from_numpy(cpu_influences(*arrays, self.sigma, first, stop))

    def _torch_influences(self, queries, source, neighbors, first: int, stop: int) -> torch.Tensor:
        """The same influences as _cpu_influences, with torch operations (GPU)."""
        padded_source = torch.cat([source, torch.full_like(source[:1], 1e6)], dim=0)
        relative = padded_source[neighbors[first:stop]] - queries[first:stop].unsqueeze(1)  # (Q, K, 3)
        # |y - x_m|^2 = |y|^2 + |x_m|^2 - 2 y.x_m: avoids the (Q, K, M, 3) difference tensor.
        sq_distances = ((relative**2).sum(dim=2, keepdim=True) + (self.kernel_points**2).sum(dim=1)
                        - 2.0 * torch.matmul(relative, self.kernel_points.T))  # (Q, K, M)
        distances = torch.sqrt(torch.clamp(sq_distances, min=0.0))
        return torch.clamp(1.0 - distances / self.sigma, min=0.0).transpose(1, 2)  # (Q, M, K)


class EncoderBlock(nn.Module):
    """Grid subsampling + KPConv ResNet block: pre-linear, KPConv, BN/LeakyReLU/linear/BN, shortcut, LeakyReLU."""

    def __init__(self, in_dim: int, out_dim: int, grid_size: float, kernel_radius: float, max_neighbors: int,
                 num_kernel_points: int, slope: float, momentum: float):
        super().__init__()
        self.grid_size = grid_size  # normalised units
        self.kernel_radius = kernel_radius  # normalised units
        self.max_neighbors = max_neighbors
        self.activation = nn.LeakyReLU(slope)
        conv_in = in_dim
        self.preactivation: nn.Module = nn.Identity()
        if in_dim > 1:
            self.preactivation = nn.Sequential(
                nn.Linear(in_dim, out_dim), nn.BatchNorm1d(out_dim, momentum=momentum), self.activation)
            conv_in = out_dim
        self.kp_conv = KPConv(conv_in, out_dim, kernel_radius, num_kernel_points)
        self.post_layer = nn.Sequential(
            nn.BatchNorm1d(out_dim, momentum=momentum), self.activation, nn.Linear(out_dim, out_dim),
            nn.BatchNorm1d(out_dim, momentum=momentum))
        self.shortcut: nn.Module = nn.Identity()
        if in_dim != out_dim:
            self.shortcut = nn.Sequential(nn.Linear(in_dim, out_dim), nn.BatchNorm1d(out_dim, momentum=momentum))

    def forward(self, points: torch.Tensor, features: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        points_np = points.detach().cpu().numpy()
        kept = grid_subsample(points_np, self.grid_size)
        neighbors = radius_neighbors(points_np, points_np[kept], self.kernel_radius, self.max_neighbors)
        kept_t = torch.from_numpy(kept).to(points.device)
        queries = points[kept_t]
        conv = self.kp_conv(queries, points, torch.from_numpy(neighbors).to(points.device),
                            self.preactivation(features))
        out = self.activation(self.shortcut(features[kept_t]) + self.post_layer(conv))
        return queries, out
