"""The numpy forward (model/inference.py) against the torch network, torch's sort order without torch, and
compress / decompress on the CPU without importing torch."""

import pickle
import subprocess
import sys
import types

import numpy as np
import pytest
import torch

from mapsqueeze.errors import ModelError
from mapsqueeze.geometry.introsort import introsort_argsort
from mapsqueeze.model import ModelConfig, build_model, load_model, save_model, shipped_models
from mapsqueeze.model.compression import CompressionModel
from mapsqueeze.model.inference import InferenceNetwork

FEATURE_TOLERANCE = 1e-4
"""Max |numpy - torch| of an embedding feature (feature spread ~1): folded batch norms and another BLAS round
differently (measured <= 3.5e-5 on the real KITTI tile)."""

POINT_TOLERANCE = 1e-5
"""Max |numpy - torch| of a decoded coordinate, normalised units (x 40 m: 0.4 mm; measured ~2e-6)."""


def street_tile(n: int, seed: int) -> np.ndarray:
    """A ground plane and two walls with 2 cm noise, normalised to a 40 m tile (float32 in [0, 1))."""
    rng = np.random.default_rng(seed)
    k = n // 3
    ground = np.c_[rng.random((k, 2)) * 36, rng.normal(0.3, 0.02, k)]
    wall = np.c_[rng.random(k) * 36, np.full(k, 12.0) + rng.normal(0, 0.02, k), rng.random(k) * 8]
    pole = np.c_[np.full(n - 2 * k, 25.0), np.full(n - 2 * k, 30.0), rng.random(n - 2 * k) * 6]
    return (np.vstack([ground, wall, pole]) / 40.0 + 0.02).astype(np.float32)


def kitti_tile(path) -> np.ndarray:
    from mapsqueeze.io import read_points

    points = read_points(path)
    local = (points - points.min(axis=0)) / 40.0
    keep = np.sort(np.random.default_rng(0).choice(len(local), 30000, replace=False))
    return local[keep].astype(np.float32)


def assert_forwards_agree(network, points: np.ndarray) -> None:
    """The torch network and the numpy forward of its weights: the same embedding points, features and decoded
    points within the tolerances, the same output count and order."""
    tensors = {k: v.numpy() for k, v in network.state_dict().items()}
    numpy_forward = InferenceNetwork(network.config, tensors)
    with torch.no_grad():
        torch_points, torch_features = network.encoder(torch.from_numpy(points))
        torch_output, _ = network.decoder(torch_points, torch_features)
    emb_points, emb_features = numpy_forward.encode(points)
    np.testing.assert_array_equal(emb_points, torch_points.numpy())
    assert np.abs(emb_features - torch_features.numpy()).max() < FEATURE_TOLERANCE
    output = numpy_forward.decode(torch_points.numpy(), torch_features.numpy())  # the same embedding
    assert output.shape == torch_output.shape
    assert np.abs(output - torch_output.numpy()).max() < POINT_TOLERANCE
    assert np.abs(numpy_forward.decode(emb_points, emb_features) - torch_output.numpy()).max() < 1e-3


@pytest.mark.parametrize("name", ["e0", "e1", "e2", "e3"])
def test_numpy_forward_matches_torch_for_every_shipped_model(name, kitti_submap):
    assert name in shipped_models()
    network = load_model(name).network
    assert_forwards_agree(network, street_tile(12000, seed=1))
    assert_forwards_agree(network, kitti_tile(kitti_submap))


@pytest.mark.parametrize("rate", ["e0", "e3"])
def test_numpy_forward_matches_torch_with_random_weights(rate):
    network = build_model(ModelConfig.for_rate(rate), seed=7).eval()
    with torch.no_grad():  # batch norms away from the identity, as after training
        for name, buffer in network.named_buffers():
            if name.endswith("running_mean"):
                buffer.normal_(0, 0.3)
            elif name.endswith("running_var"):
                buffer.uniform_(0.5, 2.0)
    assert_forwards_agree(network, street_tile(8000, seed=2))


@pytest.mark.parametrize("rate", ["e0", "e3"])
def test_decode_gradient_matches_torch_autograd(rate):
    """`decode_traced` gives `decode`'s output, and `decode_gradient` the gradient torch's autograd gives through
    the decoder (random weights: the LeakyReLUs' negative sides and tanh's slopes matter)."""
    network = build_model(ModelConfig.for_rate(rate), seed=3).eval()
    model = CompressionModel.from_network(network, "random", "")
    rng = np.random.default_rng(5)
    points = rng.random((300, 3), dtype=np.float32)  # more than one of the decoder's groups at e3
    features = rng.normal(0, 1, (300, 3)).astype(np.float32)
    output, trace = model.inference.decode_traced(points, features)
    assert np.array_equal(output, model.inference.decode(points, features))
    weights = rng.normal(0, 1, output.shape).astype(np.float32)
    torch_points, torch_features = (torch.from_numpy(a).requires_grad_(True) for a in (points, features))
    (network.decoder(torch_points, torch_features)[0] * torch.from_numpy(weights)).sum().backward()
    point_gradient, feature_gradient = model.inference.decode_gradient(trace, weights)
    np.testing.assert_allclose(point_gradient, torch_points.grad.numpy(), rtol=1e-4, atol=1e-3)
    np.testing.assert_allclose(feature_gradient, torch_features.grad.numpy(), rtol=1e-3, atol=1e-4)
    assert np.abs(feature_gradient).max() > 1e-2


def test_the_torch_passes_of_other_devices_agree_with_the_numpy_forward():
    """`torch_encode` / `torch_decode` (what a model on a GPU runs) here on the CPU network."""
    from mapsqueeze.model.autoencoder import torch_decode, torch_encode

    model = load_model("e0")
    points = street_tile(8000, seed=4)
    emb_points, emb_features = torch_encode(model.network, points)
    expected_points, expected_features = model.inference.encode(points)
    np.testing.assert_array_equal(emb_points, expected_points)
    assert np.abs(emb_features - expected_features).max() < FEATURE_TOLERANCE
    output = torch_decode(model.network, expected_points, expected_features)
    assert np.abs(output - model.inference.decode(expected_points, expected_features)).max() < POINT_TOLERANCE


def test_weights_that_do_not_match_the_architecture_are_refused(tmp_path):
    from safetensors.numpy import load_file, save_file

    save_model(build_model(ModelConfig.for_rate("e1")), tmp_path / "m")
    weights = tmp_path / "m" / "model.safetensors"
    tensors = load_file(str(weights))
    for changed, message in (({**tensors, "decoder.extra.weight": np.zeros(3, np.float32)}, "does not have"),
                             ({k: v for k, v in tensors.items() if k != "encoder.embedding.bias"}, "lack"),
                             ({**tensors, "decoder.refine.weight": np.zeros((3, 31), np.float32)}, "shape")):
        save_file(changed, str(weights))
        with pytest.raises(ModelError, match=message):
            load_model(tmp_path / "m")


def test_the_model_pickles_without_its_torch_network():
    model = load_model("e0")
    assert model.network is model.network  # built once
    copy = pickle.loads(pickle.dumps(model))
    assert copy._network is None
    points = street_tile(6000, seed=3) * 40.0
    embedding = model.encode(points)
    np.testing.assert_array_equal(copy.encode(points).features, embedding.features)


def test_compress_refine_and_decompress_on_the_cpu_import_no_torch(tmp_path):
    probe = (
        "import sys, numpy as np, mapsqueeze\n"
        "rng = np.random.default_rng(0)\n"
        "points = np.c_[rng.random((20000, 2)) * 70, rng.normal(1, 0.05, 20000)] + [1000.0, 2000.0, 0.0]\n"
        "data = mapsqueeze.compress(points, model='e1', workers=1)\n"
        "assert mapsqueeze.compress(points, model='e1', workers=1, refine_steps=1) != data\n"
        "assert len(mapsqueeze.decompress(data, workers=1)) > 0\n"
        "import mapsqueeze.codec.compress, mapsqueeze.codec.decompress, mapsqueeze.model\n"  # the workers' modules
        "print('torch' in sys.modules)\n")
    result = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    assert result.stdout.split() == ["False"]


@pytest.mark.parametrize("keys", [
    np.zeros(100, np.float32),
    np.arange(1000, dtype=np.float32),
    np.arange(1000, dtype=np.float32)[::-1].copy(),
    np.r_[np.arange(5000), np.arange(5000)[::-1]].astype(np.float32),  # organ pipe
    (np.arange(100000) % 7).astype(np.float32),  # sawtooth: long runs of equal keys
    np.random.default_rng(0).integers(0, 3, 50000).astype(np.float32),
    np.random.default_rng(1).integers(0, 2000, 30000).astype(np.float32),
    np.round(np.random.default_rng(2).random(20000) * 50) / np.float32(50),
    np.random.default_rng(3).random(17).astype(np.float32),
    np.float32(1000) + np.random.default_rng(4).random(30000).astype(np.float32) * np.float32(0.7),  # float ties
], ids=["equal", "sorted", "reversed", "organ-pipe", "sawtooth", "3-values", "2000-values", "50-levels", "17",
        "float32-ties"])
def test_introsort_orders_ties_like_torch(keys):
    expected = torch.argsort(torch.from_numpy(keys)).numpy()
    np.testing.assert_array_equal(introsort_argsort(keys), expected)


def test_introsort_handles_tiny_inputs_and_refuses_nan():
    for n in range(0, 20):
        keys = np.random.default_rng(n).integers(0, 4, n).astype(np.float64)
        np.testing.assert_array_equal(introsort_argsort(keys), torch.argsort(torch.from_numpy(keys)).numpy())
    with pytest.raises(ValueError, match="NaN"):
        introsort_argsort(np.array([1.0, np.nan]))


def test_the_activation_gives_the_same_bits_with_and_without_the_compiled_kernel(monkeypatch):
    """Compress (numba loaded) runs the decoder's bias + LeakyReLU in the encoder's compiled kernel, decompress in
    numpy's row blocks: the same bits, so the decodes the encoder measures are the decoder's."""
    from mapsqueeze.model import inference, influences

    rng = np.random.default_rng(3)
    x = rng.normal(size=(9000, 256)).astype(np.float32)
    bias = rng.normal(size=256).astype(np.float32)
    x[::5, :7] = -bias[:7]  # x + b == +0.0
    x[1::5, :3] = 0.0
    bias[8:12] = -0.0
    calls = []
    kernel = influences.bias_leaky_relu
    monkeypatch.setattr(influences, "bias_leaky_relu", lambda *args: calls.append(kernel(*args)))
    compiled, blocks = x.copy(), x.copy()
    inference._bias_leaky_relu(compiled, bias, np.float32(0.01))
    assert calls
    monkeypatch.delitem(sys.modules, "mapsqueeze.model.influences")
    inference._bias_leaky_relu(blocks, bias, np.float32(0.01))
    assert len(calls) == 1
    expected = x + bias
    expected = np.where(expected > 0, expected, expected * np.float32(0.01))
    assert np.array_equal(compiled.view(np.uint32), blocks.view(np.uint32))
    assert np.array_equal(blocks.view(np.uint32), expected.view(np.uint32))
    importing = x.copy()  # the module as another thread is importing it: in sys.modules, its kernel not yet defined
    monkeypatch.setitem(sys.modules, "mapsqueeze.model.influences", types.ModuleType("mapsqueeze.model.influences"))
    inference._bias_leaky_relu(importing, bias, np.float32(0.01))
    assert np.array_equal(importing.view(np.uint32), expected.view(np.uint32))


def test_encoder_bytes_do_not_depend_on_the_influence_parts(monkeypatch, kitti_submap):
    """The KPConv's influences are made and multiplied with the neighbours' features in parts of a chunk's queries
    (`inference.INFLUENCE_PART_ELEMENTS`); each query's product is its own BLAS call, so one query per part, the
    default parts and one part per chunk give the same embedding bits."""
    from mapsqueeze.model import inference

    model = load_model("e1")
    points = kitti_tile(kitti_submap)
    outputs = []
    for elements in (1, inference.INFLUENCE_PART_ELEMENTS, 1 << 40):
        monkeypatch.setattr(inference, "INFLUENCE_PART_ELEMENTS", elements)
        outputs.append(model.inference.encode(points))
    for emb_points, emb_features in outputs[1:]:
        np.testing.assert_array_equal(emb_points, outputs[0][0])
        np.testing.assert_array_equal(emb_features, outputs[0][1])
