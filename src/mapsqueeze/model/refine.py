"""Encode-time refinement of one tile's embedding (beyond the paper).

The encoder predicts an embedding in one pass; the decoder is what the reader will run. With the tile's points at
hand, the compressor can move the embedding towards a better reconstruction: a few Adam steps on the embedding
features and positions, minimising D_e (`mean_distance_loss`) between the frozen decoder's output and the tile's
points. The file format and the decoder are unchanged; 0 steps is the paper's encoder output. Measured on the real
submaps (BENCHMARKS.md, "Encode-time refinement"): 20 steps lower D_e by about 10 % at the same bpp.
"""

from __future__ import annotations

import contextlib

import numpy as np
import torch
from pykdtree.kdtree import KDTree
from torch.optim.adam import adam

from mapsqueeze.model.loss import mean_distance_loss

FEATURE_LR = 0.1
"""Adam step size of the embedding features (feature units; the q quantiser's step is ~0.2 of their spread)."""

POSITION_LR = 0.0005
"""Adam step size of the embedding positions, normalised units (x map_size: 2 cm per step for 40 m tiles)."""


class _Adam:
    """torch's Adam (default betas and eps) over (tensor, step size) pairs, through its functional form `adam`:
    constructing `torch.optim.Adam` imports torch._dynamo, ~2.6 s once per process."""

    def __init__(self, groups: list[tuple[torch.Tensor, float]]):
        self.groups = [(p, lr, torch.zeros_like(p), torch.zeros_like(p), torch.tensor(0.0)) for p, lr in groups]

    @torch.no_grad()
    def step(self):
        """One update from the tensors' .grad, which it then clears."""
        for p, lr, mean, mean_sq, count in self.groups:
            adam([p], [p.grad], [mean], [mean_sq], [], [count], foreach=False, capturable=False, differentiable=False,
                 fused=None, grad_scale=None, found_inf=None, has_complex=False, amsgrad=False, beta1=0.9,
                 beta2=0.999, lr=lr, weight_decay=0.0, eps=1e-8, maximize=False)
            p.grad = None


@contextlib.contextmanager
def _frozen(module: torch.nn.Module):
    """No gradients for the module's parameters inside the block (flags restored after)."""
    flags = [p.requires_grad for p in module.parameters()]
    try:
        for p in module.parameters():
            p.requires_grad_(False)
        yield module
    finally:
        for p, flag in zip(module.parameters(), flags):
            p.requires_grad_(flag)


@contextlib.contextmanager
def _deterministic(device: torch.device):
    """On a GPU, torch's deterministic kernels inside the block (the backward of a gather with repeated indices
    otherwise accumulates atomically, and 20 steps amplify that into different files); kernels without a
    deterministic version (cuBLAS without CUBLAS_WORKSPACE_CONFIG) only warn. Both of torch's settings are restored
    after. Nothing on the CPU, where the loss's gathers are deterministic already (`loss._matched_squared_distances`)
    and the first `torch.use_deterministic_algorithms` call would import torch._inductor (~2.6 s)."""
    if device.type == "cpu":
        yield
        return
    previous = (torch.are_deterministic_algorithms_enabled(), torch.is_deterministic_algorithms_warn_only_enabled())
    torch.use_deterministic_algorithms(True, warn_only=True)
    try:
        yield
    finally:
        torch.use_deterministic_algorithms(previous[0], warn_only=previous[1])


def refine_embedding(decoder: torch.nn.Module, target: torch.Tensor, points: torch.Tensor, features: torch.Tensor,
                     steps: int, feature_lr: float = FEATURE_LR, position_lr: float = POSITION_LR
                     ) -> tuple[torch.Tensor, torch.Tensor]:
    """`steps` Adam steps on (points, features) of an embedding, normalised units, towards the lowest D_e of
    decoder(points, features) against `target` (N, 3). Returns the refined (points, features), detached.

    Deterministic: neighbours from KD-trees, fixed step sizes, gathers with a fixed-order backward (CPU) or
    torch's deterministic kernels (GPU).
    """
    if steps < 0:
        raise ValueError(f"refinement steps must be >= 0, got {steps}")
    if steps == 0 or len(points) == 0 or len(target) == 0:
        return points, features
    target = target.detach()
    target_tree = KDTree(np.ascontiguousarray(target.cpu().numpy()))
    shift = torch.zeros_like(points, requires_grad=True)
    refined = features.detach().clone().requires_grad_(True)
    optimiser = _Adam([(refined, feature_lr), (shift, position_lr)])
    with _frozen(decoder), _deterministic(points.device), torch.enable_grad():
        for _ in range(steps):
            output, _ = decoder(points + shift, refined)
            mean_distance_loss(target, output, target_tree).backward()
            optimiser.step()
    return (points + shift).detach(), refined.detach()
