"""The torch paths of a GPU (`train --device cuda`, a model loaded with device="cuda": encode, refine and decode on
the torch network) run here on a simulated device (`devicesim`), which refuses what CUDA refuses: a CPU tensor in an
operation on the device, numpy of a device tensor. A device this machine lacks is one clear error."""

import numpy as np
import pytest
import torch
from devicesim import OnDevice, simulated_device
from test_inference import FEATURE_TOLERANCE, POINT_TOLERANCE, street_tile

from mapsqueeze.data.mapping import Submap, write_dataset
from mapsqueeze.errors import MapsqueezeError
from mapsqueeze.model import ModelConfig, load_model, load_network
from mapsqueeze.model.devices import CUBLAS_WORKSPACE, same_device, torch_device
from mapsqueeze.model.refine import FEATURE_LR, POSITION_LR
from mapsqueeze.model.refinetorch import _deterministic
from mapsqueeze.model.shipped import SHIPPED_DIR
from mapsqueeze.train import TrainConfig, train, weights_digest


def test_the_simulated_device_refuses_what_cuda_refuses():
    with simulated_device() as device:
        on = torch.ones(4, 3, device=device)
        assert isinstance(on, OnDevice) and on.device.type != "cpu"
        with pytest.raises(RuntimeError, match="same device"):
            on + torch.ones(4, 3)
        with pytest.raises(RuntimeError, match="same device"):
            on.index_select(0, torch.tensor([0, 2]))
        with pytest.raises(RuntimeError, match="not supported"):
            np.asarray(on)
        # as on CUDA: CPU scalars (0-d), CPU indices of tensor[indices], .cpu() and .to(device)
        assert torch.equal((on + torch.tensor(1.0)).cpu(), torch.full((4, 3), 2.0))
        assert torch.equal(on[torch.tensor([0, 2])].cpu(), torch.ones(2, 3))
        assert isinstance(torch.zeros(2).to(device), OnDevice) and type(on.cpu()) is torch.Tensor


def test_a_model_on_a_device_encodes_refines_and_decodes_as_on_the_cpu():
    """The torch network there: the KPConv influences in torch, refinement through autograd (which leaves the
    decoder's gradients alone), every result back as numpy."""
    cpu = load_model("e0")
    scale = np.float32(cpu.config.map_size)
    tile = street_tile(8000, seed=4) * scale
    expected = cpu.encode(tile)
    with simulated_device() as device:
        model = load_model("e0", device=device)
        embedding = model.encode(tile)
        refined = model.refine(tile, expected, steps=2)
        decoded = model.decode(refined.points, refined.features)
        assert all(isinstance(p, OnDevice) and p.grad is None for p in model.network.parameters())
    np.testing.assert_array_equal(embedding.points, expected.points)
    assert np.abs(embedding.features - expected.features).max() < FEATURE_TOLERANCE
    cpu_refined = cpu.refine(tile, expected, steps=2)
    np.testing.assert_allclose(refined.features, cpu_refined.features, atol=0.05 * FEATURE_LR)
    np.testing.assert_allclose(refined.points, cpu_refined.points, atol=0.05 * POSITION_LR * scale)
    assert np.abs(refined.features - expected.features).max() > 0.1  # the steps moved it
    np.testing.assert_allclose(decoded, cpu.decode(refined.points, refined.features), atol=POINT_TOLERANCE * scale)


def test_the_codec_compresses_refines_and_decompresses_with_a_model_on_a_device():
    """mapsqueeze.compress and decompress given a model there (one worker: the simulation holds in this thread)."""
    import mapsqueeze

    points = np.random.default_rng(3).random((6000, 3)) * [30, 30, 3]
    with simulated_device() as device:
        model = load_model("e1", device=device)
        data = mapsqueeze.compress(points, model=model, refine_steps=1, workers=1)
        decoded = mapsqueeze.decompress(data, model=model, workers=1)
    expected = mapsqueeze.decompress(data, workers=1)  # the same file on the CPU
    assert decoded.shape == expected.shape and np.abs(decoded - expected).max() < 1e-4  # metres


def test_refinement_keeps_torchs_deterministic_mode_on_until_its_last_thread_leaves():
    """Tile workers are threads of one process and torch's setting is global: one leaving must not turn it off
    under another."""
    device = torch.device("meta")
    first, second = _deterministic(device), _deterministic(device)
    first.__enter__()
    second.__enter__()
    first.__exit__(None, None, None)
    assert torch.are_deterministic_algorithms_enabled()
    second.__exit__(None, None, None)
    assert not torch.are_deterministic_algorithms_enabled()


@pytest.fixture
def dataset(tmp_path):
    rng = np.random.default_rng(0)
    submaps = []
    for index, split in enumerate(("train", "train", "val")):
        points = np.column_stack([rng.uniform(0, 40, 1500), rng.uniform(0, 40, 1500), rng.normal(1, 0.05, 1500)])
        submaps.append(Submap(points, np.array([20.0, 20.0, 1.0]), np.array([[0, 0, 0], [40, 40, 15.0]]), "flat",
                              index, None, split))
    write_dataset(tmp_path / "data", submaps, {})
    return tmp_path / "data"


@pytest.mark.parametrize("objective, encoder_only", [("chamfer", False), ("mean-distance", True)])
def test_training_on_a_device_steps_retimes_validates_checkpoints_and_resumes(dataset, tmp_path, objective,
                                                                              encoder_only):
    """As benchmarks/retrain.sh trains on a GPU: from a shipped model (--init), within --max-minutes."""
    out, init = tmp_path / "run", SHIPPED_DIR / "e3"
    config = ModelConfig.for_rate("e3")
    runs = (TrainConfig(epochs=2, batch_size=1, max_steps=3, max_minutes=10, objective=objective,
                        encoder_only=encoder_only),  # 3 steps: the cycle is fitted to the time
            TrainConfig(epochs=3, batch_size=1, max_steps=4, objective=objective, encoder_only=encoder_only))
    with simulated_device() as device:
        summaries = [train(dataset, out, config, cfg, device=device, init=init) for cfg in runs]
    assert [s["steps"] for s in summaries] == [3, 4]  # the second resumed from the first's last/
    assert all(s[f"best_val_{'chamfer_m2' if objective == 'chamfer' else 'mean_distance_m'}"] > 0 for s in summaries)
    trained, _ = load_network(out / "last")
    assert summaries[1]["process_weights_sha256"] == [weights_digest(trained)]
    assert weights_digest(trained) != weights_digest(load_network(init)[0])


def test_a_device_name_is_checked_before_any_work(monkeypatch):
    with pytest.raises(MapsqueezeError, match="unknown device 'gpu'"):
        torch_device("gpu")
    assert torch_device("cpu") == torch.device("cpu")
    for name in ("mps", "xpu", "meta"):  # devices torch knows that the network does not run on
        with pytest.raises(MapsqueezeError, match=f"device '{name}' is not supported: use cpu or cuda"):
            torch_device(name)
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 1)
    monkeypatch.delenv("CUBLAS_WORKSPACE_CONFIG", raising=False)
    with pytest.raises(MapsqueezeError, match="indices 0 to 0"):
        torch_device("cuda:1")
    with pytest.raises(MapsqueezeError, match="2 processes on 'cuda' need 2 GPUs"):
        torch_device("cuda", processes=2)
    assert torch_device("cuda") == torch.device("cuda")
    assert torch.cuda.is_available() and __import__("os").environ["CUBLAS_WORKSPACE_CONFIG"] == CUBLAS_WORKSPACE


def test_cuda_and_the_index_of_the_current_gpu_are_one_device_for_a_loaded_model(monkeypatch):
    """A model loaded on "cuda" runs on the current GPU: given device "cuda:0" while GPU 0 is current it is taken, on
    "cuda:1" it is refused (two GPUs seen, none there: torch.cuda answers as on a two-GPU machine)."""
    from mapsqueeze.api import _device

    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 2)
    monkeypatch.setattr(torch.cuda, "current_device", lambda: 0)
    model = load_model("e0")
    model.device = "cuda"
    assert same_device("cuda", "cuda:0") and not same_device("cuda", "cuda:1") and not same_device("cpu", "cuda")
    assert _device("cuda:0", model, None) == "cuda:0"
    with pytest.raises(MapsqueezeError, match="runs on 'cuda', not on device 'cuda:1'"):
        _device("cuda:1", model, None)
    monkeypatch.setattr(torch.cuda, "current_device", lambda: 1)
    assert _device("cuda:1", model, None) == "cuda:1"


@pytest.mark.skipif(torch.cuda.is_available(), reason="this machine has a GPU")
@pytest.mark.parametrize("args, message", [(("--device", "cuda"), "device 'cuda' is not available"),
                                           (("--device", "cuda", "--nproc", "2"), "device 'cuda' is not available"),
                                           (("--device", "gpu"), "unknown device 'gpu'")])
def test_training_on_a_device_this_machine_lacks_is_one_error_line(run_cli, dataset, tmp_path, args, message):
    code, _, err = run_cli("train", str(dataset), "-o", str(tmp_path / "run"), "--max-steps", "1", *args)
    assert code == 2 and err.strip().startswith("error:") and message in err, err
    assert len(err.strip().splitlines()) == 1 and not (tmp_path / "run").exists()


@pytest.fixture
def torch_passes(monkeypatch):
    """Counts of the torch network's passes (`autoencoder.torch_encode`, `torch_refine`, `torch_decode`): the
    branch a model on another device than the CPU takes."""
    from mapsqueeze.model import autoencoder

    counts = {}
    for name in ("torch_encode", "torch_refine", "torch_decode"):
        def counted(*args, _name=name, _pass=getattr(autoencoder, name), **kwargs):
            counts[_name] = counts.get(_name, 0) + 1
            return _pass(*args, **kwargs)

        monkeypatch.setattr(autoencoder, name, counted)
    return counts


def _street(n: int = 6000, seed: int = 3) -> np.ndarray:
    """A map of one 40 m tile (float64 metres)."""
    return np.random.default_rng(seed).random((n, 3)) * [30, 30, 3]


def test_the_api_loads_the_models_it_names_on_the_device(torch_passes):
    """compress and decompress given a device: the default model, a rate target's e0..e3 and the model named in
    the file run there (one worker: the simulation holds in this thread); the file decodes on the CPU."""
    import mapsqueeze

    points = _street()
    with simulated_device() as device:
        data = mapsqueeze.compress(points, refine_steps=1, workers=1, device=device)
        assert torch_passes["torch_encode"] == 1 and torch_passes["torch_refine"] == 1
        decodes = [torch_passes["torch_decode"]]  # the mode decision's
        decoded = mapsqueeze.decompress(data, workers=1, device=device)
        decodes.append(torch_passes["torch_decode"])
        cloud = mapsqueeze.decompress_cloud(data, model="e1", workers=1, device=device)
        decodes.append(torch_passes["torch_decode"])
        assert decodes[0] >= 1 and decodes[0] < decodes[1] < decodes[2], decodes
        encodes = torch_passes["torch_encode"]
        mapsqueeze.compress(points, max_error=1.0, workers=1, device=device)
        assert torch_passes["torch_encode"] - encodes == 4  # each of e0..e3 encodes the tile there
    expected = mapsqueeze.decompress(data, workers=1)  # on the CPU, without torch's passes
    assert decoded.shape == expected.shape == cloud.points.shape and np.abs(decoded - expected).max() < 1e-4
    assert mapsqueeze.info(data).model_id == "e1"


def test_a_loaded_model_runs_where_it_was_loaded_and_a_device_is_checked_before_any_work(tmp_path):
    import mapsqueeze

    with simulated_device() as device:
        with pytest.raises(MapsqueezeError, match="runs on 'cpu', not on device 'meta'"):
            mapsqueeze.compress(_street(), model=load_model("e0"), device=device)
        with pytest.raises(MapsqueezeError, match="with a Dask cluster"):
            mapsqueeze.decompress(b"not read", device=device, dask_scheduler="local")
    with pytest.raises(MapsqueezeError, match="unknown device 'gpu'"):
        mapsqueeze.compress_file(tmp_path / "missing.ply", tmp_path / "out.msq", device="gpu")
    assert not (tmp_path / "out.msq").exists()


def test_the_command_line_compresses_and_decompresses_on_the_device(run_cli, tmp_path, torch_passes):
    import mapsqueeze
    from mapsqueeze.io import read_points, write_points

    write_points(tmp_path / "map.ply", _street())
    with simulated_device() as device:
        code, _, err = run_cli("compress", str(tmp_path / "map.ply"), "-o", str(tmp_path / "map.msq"), "--model",
                               "e0", "--workers", "1", "--device", device)
        assert code == 0, err
        code, _, err = run_cli("decompress", str(tmp_path / "map.msq"), "-o", str(tmp_path / "out.ply"),
                               "--workers", "1", "--device", device)
        assert code == 0, err
    assert torch_passes["torch_encode"] == 1 and torch_passes["torch_decode"] >= 2  # the mode decision's, the decode
    expected = mapsqueeze.decompress(tmp_path / "map.msq", workers=1)
    decoded = read_points(tmp_path / "out.ply")
    assert decoded.shape == expected.shape and np.abs(decoded - expected).max() < 1e-4


def test_the_benchmark_runs_the_learned_codecs_on_the_device(tmp_path, torch_passes):
    import json

    from mapsqueeze.benchmark import run_benchmark
    from mapsqueeze.io import write_points

    write_points(tmp_path / "street.ply", _street())
    with simulated_device() as device:
        rows = run_benchmark([tmp_path / "street.ply"], ["mapsqueeze"], tmp_path / "out", models=["e0"],
                             log=lambda m: None, device=device)
    assert [r.setting for r in rows] == ["e0,q"] and rows[0].d_e < 1.0
    assert torch_passes["torch_encode"] == 1 and torch_passes["torch_decode"] >= 2
    assert json.loads((tmp_path / "out" / "run.json").read_text())["arguments"]["device"] == device


@pytest.mark.skipif(torch.cuda.is_available(), reason="this machine has a GPU")
@pytest.mark.parametrize("command", ["compress", "decompress", "view", "bench", "demo"])
def test_a_command_on_a_gpu_this_machine_lacks_is_one_error_line_and_no_output(run_cli, tmp_path, command):
    import mapsqueeze
    from mapsqueeze.io import write_points

    write_points(tmp_path / "map.ply", _street(3000))
    (tmp_path / "map.msq").write_bytes(mapsqueeze.compress(_street(3000), model="e0", workers=1))
    out = tmp_path / "out"
    cloud, msq = str(tmp_path / "map.ply"), str(tmp_path / "map.msq")
    args = {"compress": (cloud, "-o", f"{out}.msq"), "decompress": (msq, "-o", f"{out}.ply"),
            "view": (msq, "-o", f"{out}.html"), "bench": (cloud, "--codecs", "mapsqueeze", "-o", str(out)),
            "demo": ("-o", str(out))}[command]
    code, _, err = run_cli(command, *args, "--device", "cuda")
    assert code == 2 and err.strip().startswith("error:") and "device 'cuda' is not available" in err, err
    assert len(err.strip().splitlines()) == 1
    assert sorted(p.name for p in tmp_path.iterdir()) == ["map.msq", "map.ply"] and not out.exists()


@pytest.mark.parametrize("command", ["compress", "decompress"])
def test_a_device_torch_knows_but_the_network_does_not_run_on_is_one_error_line(run_cli, tmp_path, command):
    """--device mps (xpu, meta, ...) is refused before any work, not a traceback from the first tensor moved."""
    import mapsqueeze
    from mapsqueeze.io import write_points

    write_points(tmp_path / "map.ply", _street(3000))
    (tmp_path / "map.msq").write_bytes(mapsqueeze.compress(_street(3000), model="e0", workers=1))
    source, out = {"compress": ("map.ply", "out.msq"), "decompress": ("map.msq", "out.ply")}[command]
    code, _, err = run_cli(command, str(tmp_path / source), "-o", str(tmp_path / out), "--device", "mps")
    assert code == 2 and err == "error: device 'mps' is not supported: use cpu or cuda (cuda:N for the GPU of " \
                                "index N)\n", err
    assert not (tmp_path / out).exists()


def test_device_cpu_is_the_default_byte_for_byte(run_cli, tmp_path):
    from mapsqueeze.io import write_points

    write_points(tmp_path / "map.ply", _street())
    for name, flags in (("plain", ()), ("cpu", ("--device", "cpu"))):
        code, _, err = run_cli("compress", str(tmp_path / "map.ply"), "-o", str(tmp_path / f"{name}.msq"),
                               "--model", "e0", "--workers", "1", *flags)
        assert code == 0, err
        code, _, err = run_cli("decompress", str(tmp_path / f"{name}.msq"), "-o", str(tmp_path / f"{name}.ply"),
                               *flags)
        assert code == 0, err
    for suffix in (".msq", ".ply"):
        assert (tmp_path / f"plain{suffix}").read_bytes() == (tmp_path / f"cpu{suffix}").read_bytes()
