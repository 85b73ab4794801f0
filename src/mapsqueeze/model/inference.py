"""The autoencoder's forward pass on numpy: what compress, decompress and eval run on the CPU, without torch; and
the decoder's backward pass, which encode-time refinement follows (`model/refine.py`).

It reads the weights file's tensors under the names of the torch modules' state dict (`autoencoder.Autoencoder`,
which trains and runs on GPUs) and computes the same layers in eval mode: batch norms with their running statistics,
folded into the linear layer before them. A file with a tensor this forward does not read, one it lacks or one of
another shape is refused, so the two forwards cannot drift apart silently; the tests compare their outputs for
every shipped model (tests/test_inference.py). Matrix products run on one BLAS thread
(`one_blas_thread`) and the compiled kernels over independent rows: the output does not depend on the thread count.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass
from functools import partial

import numpy as np

from mapsqueeze.errors import ModelError
from mapsqueeze.geometry.threads import one_blas_thread, run_shared
from mapsqueeze.model.config import ModelConfig
from mapsqueeze.model.kernels import kernel_sigma, query_chunk

BATCH_NORM_EPS = 1e-5
"""torch.nn.BatchNorm1d's default epsilon, which the network uses."""

DECODE_GROUP_ROWS = 1 << 12
"""Points of the last deconvolution's input per pass: the decoder runs on groups of embedding points (each point's
children depend on it alone), so its activations (~10 MB) mostly stay in the CPU's cache whatever the tile's size.
(BLAS rounds some products of few rows differently in the last bits: the group size is part of the output.)"""

INFLUENCE_PART_ELEMENTS = 1 << 19
"""(query, kernel point, neighbour) influences computed per pass of the encoder's KPConv (2 MB of float32): they
stay in the CPU's cache until their product with the neighbours' features, which runs query by query (one BLAS
call each), so the part's size leaves the output unchanged; the product with the kernel weights keeps the chunks of
`kernels.query_chunk` (BLAS rounds products of other row counts differently)."""

LEAKY_BLOCK_ELEMENTS = 1 << 16
"""Elements per pass of the in-place bias and LeakyReLU (256 KB of float32 temporary)."""

Affine = tuple[np.ndarray, np.ndarray]
"""(W (in, out), b (out,)) float32: x -> x @ W + b."""


class _Tensors:
    """The weights file's tensors by state-dict name; `take` checks each one's shape and records it as read."""

    def __init__(self, tensors: dict[str, np.ndarray]):
        self.tensors = tensors
        self.read: set[str] = set()

    def has(self, name: str) -> bool:
        return name in self.tensors

    def take(self, name: str, shape: tuple[int, ...]) -> np.ndarray:
        if name not in self.tensors:
            raise ModelError(f"weights lack tensor {name!r}")
        value = np.asarray(self.tensors[name])
        if value.shape != shape:
            raise ModelError(f"weights tensor {name!r} has shape {value.shape}, the architecture {shape}")
        self.read.add(name)
        return value.astype(np.float32)

    def linear(self, name: str, n_in: int, n_out: int) -> Affine:
        """torch.nn.Linear `name` as (W, b)."""
        return (np.ascontiguousarray(self.take(f"{name}.weight", (n_out, n_in)).T),
                self.take(f"{name}.bias", (n_out,)))

    def batch_norm(self, name: str, n: int) -> Affine:
        """torch.nn.BatchNorm1d `name` in eval mode as a per-channel (scale, shift)."""
        self.read.add(f"{name}.num_batches_tracked")  # training state only
        scale = self.take(f"{name}.weight", (n,)) / np.sqrt(self.take(f"{name}.running_var", (n,)) + BATCH_NORM_EPS)
        shift = self.take(f"{name}.bias", (n,)) - self.take(f"{name}.running_mean", (n,)) * scale
        return scale.astype(np.float32), shift.astype(np.float32)

    def linear_batch_norm(self, linear: str, norm: str, n_in: int, n_out: int) -> Affine:
        """Linear `linear` followed by BatchNorm1d `norm`, as one (W, b)."""
        (weight, bias), (scale, shift) = self.linear(linear, n_in, n_out), self.batch_norm(norm, n_out)
        return (weight * scale).astype(np.float32), (bias * scale + shift).astype(np.float32)

    def check_all_read(self) -> None:
        unread = sorted(set(self.tensors) - self.read)
        if unread:
            raise ModelError(f"weights hold tensors the architecture does not have: {', '.join(unread[:5])}")


def _affine(x: np.ndarray, layer: Affine) -> np.ndarray:
    out = x @ layer[0]
    out += layer[1]
    return out


def _affine_leaky_relu(x: np.ndarray, layer: Affine, slope: np.float32) -> np.ndarray:
    """LeakyReLU(x @ W + b): the bias added and the activation applied in one pass over the product
    (`_bias_leaky_relu`)."""
    out = x @ layer[0]
    _bias_leaky_relu(out, layer[1], slope)
    return out


def _bias_leaky_relu(x: np.ndarray, bias: np.ndarray, slope: np.float32) -> None:
    """In place: x + b, then max(x, slope * x), which is LeakyReLU for 0 < slope < 1 (the same bits as x if x > 0
    else slope * x), in row blocks that stay in the CPU's cache between the three operations (and so does their
    temporary). Once the encoder's compiled kernels are loaded (compress; numba's start already paid), the same bits
    come from their one-pass kernel (`influences.bias_leaky_relu`, ~4x faster on the decoder's activations);
    decompress and eval load no numba for it (nor while another thread is still importing that module)."""
    kernel = getattr(sys.modules.get("mapsqueeze.model.influences"), "bias_leaky_relu", None)
    if kernel is not None:
        kernel(x, bias, slope)
        return
    rows = max(1, LEAKY_BLOCK_ELEMENTS // max(1, x.shape[1]))
    scaled = np.empty((min(rows, len(x)), x.shape[1]), dtype=x.dtype)
    for start in range(0, len(x), rows):
        block = x[start:start + rows]
        block += bias
        np.multiply(block, slope, out=scaled[:len(block)])
        np.maximum(block, scaled[:len(block)], out=block)


@dataclass
class _EncoderBlock:
    """Weights of `kpconv.EncoderBlock` (normalised units)."""

    grid_size: float
    kernel_radius: float
    max_neighbors: int
    kernel_points: np.ndarray  # (M, 3)
    sigma: float
    kernel_weights: np.ndarray  # (M * C, D): the sum over kernel points and input channels as one product
    preactivation: Affine | None  # linear + batch norm, then LeakyReLU; None when the block's input has 1 channel
    post_norm: Affine  # batch norm (scale, shift), then LeakyReLU
    post_linear: Affine  # linear + batch norm
    shortcut: Affine | None  # linear + batch norm; None: identity


@dataclass
class _Deconv:
    """Weights of `deconv.AdaptiveDeconv`: both MLPs' first layers as one product (the same input)."""

    factor: int
    hidden: int
    first: Affine  # (in, 2 * hidden): offset MLP's hidden units, then the feature MLP's
    offset: Affine  # (hidden, 3 * factor)
    feature: Affine  # (hidden, out * factor)


class InferenceNetwork:
    """Encoder and decoder of one rate point on numpy; coordinates normalised (tile-local metres / map_size)."""

    def __init__(self, config: ModelConfig, tensors: dict[str, np.ndarray]):
        self.config = config
        self.slope = np.float32(config.leaky_relu_slope)
        self.offset_scale = np.float32(config.decoder_kernel_radius)
        weights = _Tensors(tensors)
        self.encoder = self._encoder_blocks(config, weights)
        self.embedding = weights.linear("encoder.embedding", config.encoder_dims[-1], config.embedding_dim)
        dims = [config.embedding_dim] + [config.decoder_dim] * len(config.upsampling_factors)
        self.decoder = [self._deconv(weights, f"decoder.blocks.{i}", dims[i], dims[i + 1], factor)
                        for i, factor in enumerate(config.upsampling_factors)]
        self.refine = weights.linear("decoder.refine", config.decoder_dim, 3)
        weights.check_all_read()

    @staticmethod
    def _encoder_blocks(config: ModelConfig, weights: _Tensors) -> list[_EncoderBlock]:
        dims = (1,) + config.encoder_dims
        m = config.num_kernel_points
        blocks = []
        for i, (grid, radius) in enumerate(zip(config.block_grid_sizes(), config.block_kernel_radii())):
            name, n_in, n_out = f"encoder.blocks.{i}", dims[i], dims[i + 1]
            conv_in = n_out if n_in > 1 else n_in
            radius = radius / config.map_size
            blocks.append(_EncoderBlock(
                grid / config.map_size, radius, config.max_neighbors[i],
                weights.take(f"{name}.kp_conv.kernel_points", (m, 3)), kernel_sigma(radius, m),
                weights.take(f"{name}.kp_conv.weights", (m, conv_in, n_out)).reshape(m * conv_in, n_out),
                weights.linear_batch_norm(f"{name}.preactivation.0", f"{name}.preactivation.1", n_in, n_out)
                if n_in > 1 else None,
                weights.batch_norm(f"{name}.post_layer.0", n_out),
                weights.linear_batch_norm(f"{name}.post_layer.2", f"{name}.post_layer.3", n_out, n_out),
                weights.linear_batch_norm(f"{name}.shortcut.0", f"{name}.shortcut.1", n_in, n_out)
                if n_in != n_out else None))
        return blocks

    def _deconv(self, weights: _Tensors, name: str, n_in: int, n_out: int, factor: int) -> _Deconv:
        hidden = self.config.decoder_hidden
        offset_first = weights.linear(f"{name}.offset_mlp.0", n_in, hidden)
        feature_first = weights.linear(f"{name}.feature_mlp.0", n_in, hidden)
        first = (np.ascontiguousarray(np.concatenate([offset_first[0], feature_first[0]], axis=1)),
                 np.concatenate([offset_first[1], feature_first[1]]))
        return _Deconv(factor, hidden, first, weights.linear(f"{name}.offset_mlp.2", hidden, 3 * factor),
                       weights.linear(f"{name}.feature_mlp.2", hidden, n_out * factor))

    def encode(self, points: np.ndarray, compiled: bool = True) -> tuple[np.ndarray, np.ndarray]:
        """points (N, 3) float32 normalised -> embedding points (M, 3), features (M, embedding_dim) float32.
        compiled=False runs numpy's versions of the compiled kernels (`geometry.gridnumpy`,
        `influencesnumpy`): the same bytes, no numba loaded (small maps, `codec.compress.NUMPY_KERNEL_POINTS`)."""
        points = np.ascontiguousarray(points, dtype=np.float32)
        features = np.ones((len(points), 1), dtype=np.float32)  # occupancy
        with one_blas_thread():
            for block in self.encoder:
                points, features = self._encoder_block(block, points, features, compiled)
            return points, _affine(features, self.embedding)

    def _encoder_block(self, block: _EncoderBlock, points: np.ndarray, features: np.ndarray, compiled: bool = True):
        """`kpconv.EncoderBlock.forward`: grid subsampling, KPConv of the capped radius neighbours, ResNet sum."""
        if compiled:
            from mapsqueeze.geometry.grid import grid_subsample, radius_neighbors  # numba: the encoder's alone
            from mapsqueeze.model.influences import bias_leaky_relu, cpu_influences
        else:
            from mapsqueeze.geometry.gridnumpy import grid_subsample, radius_neighbors
            from mapsqueeze.model.influencesnumpy import cpu_influences

            bias_leaky_relu = _bias_leaky_relu

        kept = grid_subsample(points, block.grid_size)
        queries = np.ascontiguousarray(points[kept])
        neighbors = radius_neighbors(points, queries, block.kernel_radius, block.max_neighbors,
                                     np.int32 if len(points) < 2**31 else np.int64)
        conv_input = features if block.preactivation is None else _affine_leaky_relu(
            features, block.preactivation, self.slope)
        padded = np.concatenate([conv_input, np.zeros((1, conv_input.shape[1]), dtype=np.float32)])
        conv = np.empty((len(queries), block.kernel_weights.shape[1]), dtype=np.float32)
        n_kernel, n_neighbors = len(block.kernel_points), neighbors.shape[1]
        chunk = query_chunk(n_neighbors, n_kernel)
        part = max(1, INFLUENCE_PART_ELEMENTS // max(1, n_neighbors * n_kernel))
        influences = np.empty((min(part, len(queries)), n_kernel, n_neighbors), dtype=np.float32)
        weighted = np.empty((min(chunk, len(queries)), n_kernel, padded.shape[1]), dtype=np.float32)  # (Q, M, C)
        for first in range(0, len(queries), chunk):
            stop = min(len(queries), first + chunk)
            for start in range(first, stop, part):  # per query, the same product whatever the part
                end = min(stop, start + part)
                cpu_influences(queries, points, neighbors, block.kernel_points, block.sigma, start, end,
                               influences[:end - start])
                np.matmul(influences[:end - start], np.take(padded, neighbors[start:end], axis=0),
                          out=weighted[start - first:end - first])
            conv[first:stop] = weighted[:stop - first].reshape(stop - first, -1) @ block.kernel_weights
        conv *= block.post_norm[0]
        bias_leaky_relu(conv, block.post_norm[1], self.slope)
        out = _affine(conv, block.post_linear)
        out += features[kept] if block.shortcut is None else _affine(features[kept], block.shortcut)
        bias_leaky_relu(out, np.zeros(out.shape[1], dtype=np.float32), self.slope)
        return queries, out

    def decode(self, points: np.ndarray, features: np.ndarray) -> np.ndarray:
        """Embedding points (M, 3) and features (M, embedding_dim), normalised -> output points (M x prod(K_i), 3)
        float32 normalised, children in the order of their parents."""
        return self._decode(points, features, None)

    def decode_traced(self, points: np.ndarray, features: np.ndarray) -> tuple[np.ndarray, list]:
        """`decode`'s output (the same groups, the same values) and what `decode_gradient` needs of the pass: per
        group and deconvolution, where the LeakyReLUs' inputs are > 0 (bool) and the offsets' tanh values."""
        trace: list = [[] for _ in range(0, len(points), self._decode_groups()[0])]
        return self._decode(points, features, trace), trace

    def _decode(self, points: np.ndarray, features: np.ndarray, trace: list | None) -> np.ndarray:
        """`decode`, each group's trace appended to trace[group] unless trace is None."""
        points = np.ascontiguousarray(points, dtype=np.float32)
        features = np.ascontiguousarray(features, dtype=np.float32)
        group, children = self._decode_groups()
        out = np.empty((len(points) * children, 3), dtype=np.float32)
        tasks = [partial(self._decode_group, points[start:start + group], features[start:start + group],
                         out[start * children:(start + group) * children], None if trace is None else trace[i])
                 for i, start in enumerate(range(0, len(points), group))]
        with one_blas_thread():
            run_shared(tasks)  # the groups are independent: idle decoding threads may take some
        return out

    def _decode_group(self, points: np.ndarray, features: np.ndarray, out: np.ndarray, kept: list | None) -> None:
        """The decoder on a group of embedding points, written into `out` (each deconvolution's trace appended to
        `kept` unless it is None)."""
        for block in self.decoder:
            points, features = self._deconv_forward(block, points, features, kept)
        np.matmul(features, self.refine[0], out=out)
        for axis in range(3):  # column by column: numpy's (K, 3) + (3,) runs a 3-long inner loop per row
            out[:, axis] += self.refine[1][axis]
        out += points

    def decode_gradient(self, trace: list, output_gradient: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The gradient of a function of the decoder's output with respect to the embedding: given the trace of
        `decode_traced(points, features)` and that function's gradient with respect to its output (same shape and
        order), the gradients with respect to `points` and `features` (float32; backpropagation through the
        decoder group by group: each embedding point's gradient comes from its own children alone)."""
        output_gradient = np.ascontiguousarray(output_gradient, dtype=np.float32)
        group, children = self._decode_groups()
        n_points = len(output_gradient) // children
        point_gradient = np.empty((n_points, 3), dtype=np.float32)
        feature_gradient = np.empty((n_points, self.config.embedding_dim), dtype=np.float32)
        tasks = [partial(self._gradient_group, trace[i], output_gradient[start * children:(start + group) * children],
                         point_gradient[start:start + group], feature_gradient[start:start + group])
                 for i, start in enumerate(range(0, n_points, group))]
        with one_blas_thread():
            run_shared(tasks)
        return point_gradient, feature_gradient

    def _decode_groups(self) -> tuple[int, int]:
        """(embedding points per group of `decode`, output points per embedding point)."""
        factors = self.config.upsampling_factors
        group = max(1, DECODE_GROUP_ROWS // int(np.prod(factors[:-1], dtype=np.int64)))
        return group, int(np.prod(factors, dtype=np.int64))

    def _gradient_group(self, kept: list, output_gradient: np.ndarray, point_gradient: np.ndarray,
                        feature_gradient: np.ndarray) -> None:
        """`decode_gradient` on a group of embedding points, written into the two gradient arrays."""
        grad_points = output_gradient  # the output is the last level's points plus a function of its features
        grad_features = output_gradient @ np.ascontiguousarray(self.refine[0].T)
        for block, (hidden_on, offsets, children_on) in zip(reversed(self.decoder), reversed(kept)):
            n = len(offsets)
            grad_children = grad_features.reshape(n, -1)
            grad_children *= self._leaky_slopes(children_on.reshape(n, -1))
            grad_offsets = grad_points.reshape(n, -1) * self.offset_scale
            grad_offsets *= 1 - offsets * offsets  # tanh'
            grad_hidden = np.empty((n, 2 * block.hidden), dtype=np.float32)
            np.matmul(grad_offsets, block.offset[0].T, out=grad_hidden[:, :block.hidden])
            np.matmul(grad_children, block.feature[0].T, out=grad_hidden[:, block.hidden:])
            grad_hidden *= self._leaky_slopes(hidden_on)
            grad_features = grad_hidden @ block.first[0].T
            grad_points = grad_points.reshape(n, block.factor, 3).sum(axis=1)
        point_gradient[:] = grad_points
        feature_gradient[:] = grad_features

    def _leaky_slopes(self, positive: np.ndarray) -> np.ndarray:
        """LeakyReLU's derivative where its input was > 0 (`positive`) or not: 1 or the slope (float32; the
        arithmetic on the bools' bytes is ~5x faster than numpy's where)."""
        slopes = positive.view(np.uint8) * (np.float32(1) - self.slope)
        slopes += self.slope
        return slopes

    def _deconv_forward(self, block: _Deconv, points: np.ndarray, features: np.ndarray, kept: list | None = None
                        ) -> tuple[np.ndarray, np.ndarray]:
        """`deconv.AdaptiveDeconv.forward`: each point's `factor` children (points, features); unless `kept` is
        None, (hidden > 0, tanh offsets, children's features > 0) appended to it (`decode_traced`)."""
        n = len(points)
        hidden = _affine_leaky_relu(features, block.first, self.slope)
        tanh = _affine(hidden[:, :block.hidden], block.offset)
        np.tanh(tanh, out=tanh)
        if kept is None:
            tanh *= self.offset_scale
            offsets = tanh
        else:
            offsets = tanh * self.offset_scale
        offsets = offsets.reshape(n, block.factor, 3)
        offsets += points[:, None, :]
        children = _affine_leaky_relu(hidden[:, block.hidden:], block.feature, self.slope)
        if kept is not None:
            kept.append((hidden > 0, tanh, children > 0))
        return offsets.reshape(n * block.factor, 3), children.reshape(n * block.factor, -1)
