"""Encode-time refinement of one tile's embedding (beyond the paper).

The encoder predicts an embedding in one pass; the decoder is what the reader will run. With the tile's points at
hand, the compressor can move the embedding towards a better reconstruction: a few Adam steps on the embedding
features and positions, minimising D_e (`loss.mean_distance_loss`) between the frozen decoder's output and the
tile's points. The file format and the decoder are unchanged; 0 steps is the paper's encoder output. Measured on the
real submaps (BENCHMARKS.md, "Encode-time refinement"): 20 steps lower D_e by about 10 % at the same bpp.

Numpy throughout, without torch: each step is the numpy decode keeping a compact trace (`InferenceNetwork.
decode_traced`: the LeakyReLUs' signs as bools and the tanh values, about a tenth of the activations), the nearest
neighbours both ways from KD-trees, the gradient of D_e with respect to the output, its backpropagation to the
embedding (`InferenceNetwork.decode_gradient`), then torch's Adam update (default betas and eps) written out.

A model whose configuration gives a dead zone (`ModelConfig.refine_dead_zone_m`: the shipped e0's 7.5 cm) leaves
the distances within it out of the objective (each distance d counts as max(d - dead zone, 0)): points already that
near their neighbour stop pulling, and the steps go to the ones that miss the IoU's voxels.
"""

from __future__ import annotations

import numpy as np
from pykdtree.kdtree import KDTree

from mapsqueeze.model.inference import InferenceNetwork

FEATURE_LR = 0.1
"""Adam step size of the embedding features (feature units; the q quantiser's step is ~0.2 of their spread)."""

POSITION_LR = 0.0005
"""Adam step size of the embedding positions, normalised units (x map_size: 2 cm per step for 40 m tiles)."""

ADAM_BETAS = (0.9, 0.999)
ADAM_EPS = 1e-8

DISTANCE_EPS = 1e-12
"""Added to squared distances under the square root: keeps the gradient finite where a point sits on its
neighbour (as `loss.mean_distance_loss`)."""


class _Adam:
    """Adam (torch.optim.Adam's update in float32, without weight decay or amsgrad) of one array."""

    def __init__(self, value: np.ndarray, lr: float):
        self.value, self.lr, self.count = value, lr, 0
        self.mean = np.zeros_like(value)
        self.mean_sq = np.zeros_like(value)

    def step(self, gradient: np.ndarray) -> None:
        beta1, beta2 = ADAM_BETAS
        self.count += 1
        self.mean += (gradient - self.mean) * np.float32(1 - beta1)
        self.mean_sq *= np.float32(beta2)
        self.mean_sq += np.float32(1 - beta2) * gradient * gradient
        denominator = np.sqrt(self.mean_sq) / np.float32(np.sqrt(1 - beta2 ** self.count)) + np.float32(ADAM_EPS)
        self.value -= np.float32(self.lr / (1 - beta1 ** self.count)) * self.mean / denominator


def distance_gradient(target: np.ndarray, target_tree: KDTree, output: np.ndarray, dead_zone: float = 0.0
                      ) -> np.ndarray:
    """The gradient of D_e (`loss.mean_distance_loss`: half the mean distance of every output point to its nearest
    target point, plus half that of every target point to its nearest output point; with a dead zone z > 0 each
    distance d counts as max(d - z, 0)) with respect to `output` (K, 3) float32; the sums over target points sharing
    a nearest output point run in target order (`np.bincount`)."""
    _, to_target = target_tree.query(output, k=1)
    _, to_output = KDTree(output).query(target, k=1)
    to_output = to_output.astype(np.int64)
    away = output - target[to_target]
    gradient = away * _distance_weights(away, 0.5 / len(output), dead_zone)[:, None]
    towards = output[to_output] - target
    towards *= _distance_weights(towards, 0.5 / len(target), dead_zone)[:, None]
    for axis in range(3):
        gradient[:, axis] += np.bincount(to_output, towards[:, axis], len(output)).astype(np.float32)
    return gradient


def _distance_weights(offsets: np.ndarray, scale: float, dead_zone: float) -> np.ndarray:
    """scale / |offset| of each (K, 3) offset (d max(|o| - dead_zone, 0) / do = o / |o| where |o| > dead_zone), 0
    within the dead zone."""
    distances = np.sqrt((offsets * offsets).sum(axis=1) + DISTANCE_EPS)
    weights = scale / distances
    if dead_zone > 0:
        weights[distances <= dead_zone] = 0
    return weights


def refine_embedding(network: InferenceNetwork, target: np.ndarray, points: np.ndarray, features: np.ndarray,
                     steps: int, feature_lr: float = FEATURE_LR, position_lr: float = POSITION_LR,
                     dead_zone: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """`steps` Adam steps on (points, features) of an embedding, normalised float32 arrays, towards the lowest D_e
    of network.decode(points, features) against `target` (N, 3), its distances less `dead_zone` (normalised units,
    `distance_gradient`). Returns the refined (points, features), new arrays.

    Deterministic whatever the thread count: the decode and its gradient on fixed groups with one BLAS thread,
    neighbours from KD-trees, fixed step sizes, sums in a fixed order.
    """
    if steps < 0:
        raise ValueError(f"refinement steps must be >= 0, got {steps}")
    points = np.array(points, dtype=np.float32)
    features = np.array(features, dtype=np.float32)
    if steps == 0 or len(points) == 0 or len(target) == 0:
        return points, features
    target = np.ascontiguousarray(target, dtype=np.float32)
    target_tree = KDTree(target)
    shift = np.zeros_like(points)
    shifts, refined = _Adam(shift, position_lr), _Adam(features, feature_lr)
    for _ in range(steps):
        output, trace = network.decode_traced(points + shift, features)
        point_gradient, feature_gradient = network.decode_gradient(
            trace, distance_gradient(target, target_tree, output, dead_zone))
        del output, trace
        refined.step(feature_gradient)
        shifts.step(point_gradient)
    return points + shift, features
