"""Decoder: adaptive point deconvolutions (paper Sec. III, eq. 3-4, Fig. 3)."""

from __future__ import annotations

import torch
from torch import nn


class AdaptiveDeconv(nn.Module):
    """Each point spawns K children: x_k = x + r * tanh(MLP_k(f)), f_k = LeakyReLU(MLP_k(f))."""

    def __init__(self, in_dim: int, out_dim: int, factor: int, kernel_radius: float, hidden: int, slope: float):
        super().__init__()
        self.factor = factor
        self.out_dim = out_dim
        self.kernel_radius = kernel_radius  # normalised units
        self.offset_mlp = nn.Sequential(
            nn.Linear(in_dim, hidden), nn.LeakyReLU(slope), nn.Linear(hidden, 3 * factor), nn.Tanh())
        self.feature_mlp = nn.Sequential(
            nn.Linear(in_dim, hidden), nn.LeakyReLU(slope), nn.Linear(hidden, out_dim * factor), nn.LeakyReLU(slope))

    def forward(self, points: torch.Tensor, features: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        n = points.shape[0]
        offsets = self.offset_mlp(features).reshape(n, self.factor, 3) * self.kernel_radius
        children = (points.unsqueeze(1) + offsets).reshape(n * self.factor, 3)
        child_features = self.feature_mlp(features).reshape(n * self.factor, self.out_dim)
        return children, child_features
