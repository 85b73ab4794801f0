"""The numpy-level model the codec calls: encode, refine and decode one tile in tile-local metres."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mapsqueeze.errors import ModelError
from mapsqueeze.geometry.resample import resample_to_count
from mapsqueeze.model.config import ModelConfig
from mapsqueeze.model.inference import InferenceNetwork


@dataclass
class Embedding:
    """The compressed form of one tile: points (M,3) float32 tile-local metres, features (M,D) float32."""

    points: np.ndarray
    features: np.ndarray


class CompressionModel:
    """A trained autoencoder with a numpy API in tile-local metres.

    On the CPU, encode, refine and decode run `InferenceNetwork` (numpy, no torch); encode, refine and decode on
    another device (e.g. "cuda") run the torch network built from the same tensors (`network`, made on first use).
    Pickles without the torch network, so Dask workers that only encode and decode never import torch.
    """

    def __init__(self, config: ModelConfig, tensors: dict[str, np.ndarray], model_id: str, weights_sha256: str,
                 device: str = "cpu"):
        self.config = config
        self.tensors = tensors
        self.model_id = model_id
        self.weights_sha256 = weights_sha256
        self.device = str(device)
        self.inference = InferenceNetwork(config, tensors)  # also checks the tensors against the architecture
        self._network = None

    @classmethod
    def from_network(cls, network, model_id: str, weights_sha256: str, device: str = "cpu") -> CompressionModel:
        """The model of a torch `Autoencoder`'s current weights."""
        tensors = {k: v.detach().cpu().numpy().copy() for k, v in network.state_dict().items()}
        return cls(network.config, tensors, model_id, weights_sha256, device)

    @property
    def network(self):
        """The torch `Autoencoder` of these weights on `device`, in eval mode (imports torch); MapsqueezeError when
        this machine lacks the device (`devices.torch_device`)."""
        if self._network is None:
            from mapsqueeze.model.checkpoint import network_from_tensors
            from mapsqueeze.model.devices import torch_device

            device = torch_device(self.device)
            self._network = network_from_tensors(self.config, self.tensors).to(device).eval()
        return self._network

    def on_cpu(self) -> CompressionModel:
        """This model with the numpy forward on the CPU (itself when it runs there): the decoder that defines the
        attribute field's support, so that a file written on any device has the same support everywhere."""
        if self.device == "cpu":
            return self
        return CompressionModel(self.config, self.tensors, self.model_id, self.weights_sha256, "cpu")

    def __getstate__(self) -> dict:
        return {**self.__dict__, "_network": None}

    def select_input(self, points_local: np.ndarray) -> np.ndarray:
        """At most config.max_input_points points, drawn with a fixed seed (deterministic encoding)."""
        if len(points_local) <= self.config.max_input_points:
            return points_local
        rng = np.random.default_rng(0)
        keep = np.sort(rng.choice(len(points_local), self.config.max_input_points, replace=False))
        return points_local[keep]

    def encode(self, points_local: np.ndarray, compiled: bool = True) -> Embedding:
        """Tile-local points (N,3) metres -> embedding (positions in metres, features). Like `refine` and `decode`,
        the same bytes whatever the thread count. compiled=False: on the CPU, numpy's versions of the encoder's
        compiled kernels (the same bytes without loading numba; `InferenceNetwork.encode`)."""
        points = np.asarray(self.select_input(points_local), dtype=np.float32) / self._scale
        if self.device == "cpu":
            return self._embedding(*self.inference.encode(points, compiled))
        from mapsqueeze.model.autoencoder import torch_encode

        return self._embedding(*torch_encode(self.network, points))

    def refine(self, points_local: np.ndarray, embedding: Embedding, steps: int) -> Embedding:
        """The embedding of these tile-local points after `steps` steps of encode-time refinement towards a lower
        D_e of the decoder's output against all of them (not only the encoder's max_input_points;
        `refine.refine_embedding` with the configuration's `refine_dead_zone_m`: same format, ~0.4 s a step for a
        40 m tile on one core). On another device the same steps through torch's autograd there
        (`autoencoder.torch_refine`), which gives the same rate points within float32 rounding, not the same
        bytes."""
        points, features = self._normalised_embedding(embedding.points, embedding.features)
        target = np.asarray(points_local, dtype=np.float32) / self._scale  # every point
        from mapsqueeze.model.refine import refine_embedding

        dead_zone = self.config.refine_dead_zone_m / float(self._scale)  # the model's own, whatever its name
        if self.device == "cpu":
            return self._embedding(*refine_embedding(self.inference, target, points, features, steps,
                                                     dead_zone=dead_zone))
        from mapsqueeze.model.autoencoder import torch_refine

        return self._embedding(*torch_refine(self.network, target, points, features, steps, dead_zone))

    def decode(self, points: np.ndarray, features: np.ndarray, n_points: int | None = None) -> np.ndarray:
        """Embedding -> dense cloud (K,3) float32 tile-local metres.

        n_points=None gives the native count (M x prod(K_i)). A smaller count keeps an evenly spread deterministic
        subset (`resample_to_count`); a larger one adds midpoints between each output point and its nearest
        neighbours within 2 m, copies where it has none (arbitrary density). Raises ModelError if the network outputs a non-finite coordinate.
        """
        if len(points) == 0:
            return np.zeros((0, 3), dtype=np.float32)
        p, f = self._normalised_embedding(points, features)
        if self.device == "cpu":
            output = self.inference.decode(p, f)
        else:
            from mapsqueeze.model.autoencoder import torch_decode

            output = torch_decode(self.network, p, f)
        cloud = np.multiply(output, self._scale, out=output if output.dtype == np.float32 else None)
        if not np.isfinite(cloud).all():
            raise ModelError(f"model {self.model_id!r} decoded non-finite coordinates (broken weights?)")
        return resample_to_count(cloud, n_points).astype(np.float32, copy=False)

    @property
    def _scale(self) -> np.float32:
        return np.float32(self.config.map_size)

    def _normalised_embedding(self, points: np.ndarray, features: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return (np.ascontiguousarray(points, dtype=np.float32) / self._scale,
                np.ascontiguousarray(features, dtype=np.float32))

    def _embedding(self, points: np.ndarray, features: np.ndarray) -> Embedding:
        return Embedding((points * self._scale).astype(np.float32), features.astype(np.float32))
