"""Encode-time refinement on a torch device (`--device cuda`): the steps of `refine.refine_embedding` (Adam on the
embedding's features and positions, the same step sizes and objective, D_e of the frozen decoder's output against
every point of the tile) through torch's autograd on the network's device. The CPU runs the numpy version, which
needs no torch; the two give the same rate points within float32 rounding (tests/test_model.py).
"""

from __future__ import annotations

import contextlib
import threading

import numpy as np
import torch
from pykdtree.kdtree import KDTree
from torch.optim.adam import adam

from mapsqueeze.model.loss import mean_distance_loss
from mapsqueeze.model.refine import ADAM_BETAS, ADAM_EPS, FEATURE_LR, POSITION_LR


class _Adam:
    """torch's Adam over (tensor, step size) pairs through its functional form `adam`: constructing
    `torch.optim.Adam` imports torch._dynamo, ~2.6 s once per process."""

    def __init__(self, groups: list[tuple[torch.Tensor, float]]):
        self.groups = [(p, lr, torch.zeros_like(p), torch.zeros_like(p), torch.tensor(0.0)) for p, lr in groups]

    @torch.no_grad()
    def step(self, gradients: tuple[torch.Tensor, ...]):
        """One update of each tensor by its gradient (in the groups' order). The step counts stay on the CPU, as
        torch.optim.Adam keeps them."""
        for (p, lr, mean, mean_sq, count), gradient in zip(self.groups, gradients, strict=True):
            adam([p], [gradient], [mean], [mean_sq], [], [count], foreach=False, capturable=False,
                 differentiable=False, fused=None, grad_scale=None, found_inf=None, has_complex=False, amsgrad=False,
                 beta1=ADAM_BETAS[0], beta2=ADAM_BETAS[1], lr=lr, weight_decay=0.0, eps=ADAM_EPS, maximize=False)


_deterministic_lock = threading.Lock()
_deterministic_users = 0
_settings_before = (False, False)


@contextlib.contextmanager
def _deterministic(device: torch.device):
    """On a GPU, torch's deterministic kernels inside the block (the backward of a gather with repeated indices
    otherwise accumulates atomically, and the steps amplify that into different files); kernels without a
    deterministic version only warn. torch's setting is global: blocks of several threads (a pool of tile workers)
    share it, and the last one out restores what the first one found. Nothing on the CPU, where the loss's gathers
    are deterministic already and the first call would import torch._inductor (~2.6 s)."""
    global _deterministic_users, _settings_before
    if device.type == "cpu":
        yield
        return
    with _deterministic_lock:
        if _deterministic_users == 0:
            _settings_before = (torch.are_deterministic_algorithms_enabled(),
                                torch.is_deterministic_algorithms_warn_only_enabled())
            torch.use_deterministic_algorithms(True, warn_only=True)
        _deterministic_users += 1
    try:
        yield
    finally:
        with _deterministic_lock:
            _deterministic_users -= 1
            if _deterministic_users == 0:
                torch.use_deterministic_algorithms(_settings_before[0], warn_only=_settings_before[1])


def refine_embedding_torch(decoder: torch.nn.Module, target: torch.Tensor, points: torch.Tensor,
                           features: torch.Tensor, steps: int, dead_zone: float = 0.0
                           ) -> tuple[torch.Tensor, torch.Tensor]:
    """`steps` Adam steps on (points, features), normalised tensors on the decoder's device, towards the lowest D_e
    of decoder(points, features) against `target` (N, 3), its distances less `dead_zone` (`refine.distance_gradient`).
    Returns the refined (points, features), detached. The decoder is left as it is: the gradients are taken with
    respect to the embedding alone (`torch.autograd.grad`), so threads may refine with one decoder at once."""
    if steps < 0:
        raise ValueError(f"refinement steps must be >= 0, got {steps}")
    if steps == 0 or len(points) == 0 or len(target) == 0:
        return points, features
    target = target.detach()
    target_tree = KDTree(np.ascontiguousarray(target.cpu().numpy()))
    shift = torch.zeros_like(points, requires_grad=True)
    refined = features.detach().clone().requires_grad_(True)
    optimiser = _Adam([(refined, FEATURE_LR), (shift, POSITION_LR)])
    with _deterministic(points.device), torch.enable_grad():
        for _ in range(steps):
            output, _ = decoder(points + shift, refined)
            optimiser.step(torch.autograd.grad(mean_distance_loss(target, output, target_tree, dead_zone),
                                               (refined, shift)))
    return (points + shift).detach(), refined.detach()
