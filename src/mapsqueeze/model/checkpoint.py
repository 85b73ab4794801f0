"""The torch network and its weights on disk: saving, loading (`shipped` reads them without torch), import of the
reference checkpoints."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import torch
from safetensors.torch import save_file

from mapsqueeze.errors import ModelError
from mapsqueeze.model.autoencoder import Autoencoder
from mapsqueeze.model.config import ModelConfig
from mapsqueeze.model.shipped import CONFIG_FILE, WEIGHTS_FILE, read_weights


def save_model(network: Autoencoder, out_dir: Path) -> Path:
    """Write config.json + model.safetensors into out_dir (atomic per file). Returns out_dir."""
    from mapsqueeze.io import atomic_output

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    tensors = {k: v.detach().cpu().contiguous() for k, v in network.state_dict().items()}
    with atomic_output(out_dir / WEIGHTS_FILE) as tmp:
        save_file(tensors, str(tmp), metadata={"format": "mapsqueeze-autoencoder"})
    with atomic_output(out_dir / CONFIG_FILE) as tmp:
        Path(tmp).write_text(network.config.to_json())
    return out_dir


def network_from_tensors(config: ModelConfig, tensors: dict[str, np.ndarray]) -> Autoencoder:
    """The torch network of a config and its tensors by state-dict name (every tensor, none missing)."""
    network = Autoencoder(config)
    try:
        network.load_state_dict({k: torch.from_numpy(np.array(v)) for k, v in tensors.items()}, strict=True)
    except RuntimeError as exc:
        raise ModelError(str(exc).splitlines()[0]) from None
    return network


def load_network(model_dir: Path) -> tuple[Autoencoder, str]:
    """Build the network from config.json and load its weights. Returns (network, SHA-256 of the weights file)."""
    config, tensors, sha = read_weights(model_dir)
    try:
        return network_from_tensors(config, tensors), sha
    except ModelError as exc:
        raise ModelError(f"cannot load weights {Path(model_dir) / WEIGHTS_FILE}: {exc}") from None


# --- import of the reference implementation's released checkpoints ------------------------------------------------

def _reference_key(key: str, part: str) -> str:
    """Map a reference state-dict key (enc_best.pth / dec_best.pth) to this project's module names."""
    if part == "encoder":
        key = re.sub(r"^blocks\.0\.(\d+)\.", r"encoder.blocks.\1.", key)
        key = re.sub(r"^blocks\.1\.blocks\.0\.", "encoder.embedding.", key)
    else:
        key = re.sub(r"^blocks\.0\.(\d+)\.transl_nn\.", r"decoder.blocks.\1.offset_mlp.", key)
        key = re.sub(r"^blocks\.0\.(\d+)\.feature_nn\.", r"decoder.blocks.\1.feature_mlp.", key)
        key = re.sub(r"^blocks\.1\.blocks\.0\.", "decoder.refine.", key)
    return key


def config_from_reference_yaml(yaml_path: Path) -> ModelConfig:
    """The ModelConfig equivalent to a reference eX.yaml."""
    import yaml

    cfg = yaml.safe_load(Path(yaml_path).read_text())
    try:
        enc = cfg["network"]["encoder_blocks"][0]["parameters"]
        dec = cfg["network"]["decoder_blocks"][0]["parameters"]
        return ModelConfig(
            name=str(cfg["train"]["experiment_id"]),
            subsampling_dist=float(enc["subsampling_dist"]),
            map_size=float(enc["map_size"]),
            tile_size=tuple(cfg["grid"]["size"]),
            encoder_dims=tuple(enc["out_fdim"]),
            subsampling_factors=tuple(enc["subsampling_factor"]),
            max_neighbors=tuple(enc["max_nr_neighbors"]),
            kernel_radius_factor=float(enc["kernel_radius"]),
            min_kernel_radius=float(enc["min_kernel_radius"]),
            num_kernel_points=int(enc["num_kernel_points"]),
            embedding_dim=int(cfg["network"]["encoder_blocks"][1]["parameters"]["out_fdim"]),
            decoder_dim=int(dec["out_fdim"]),
            decoder_hidden=int(dec["inter_fdim"]),
            decoder_kernel_radius=float(dec["kernel_radius"]),
            density_a=float(dec["subsampling_fct_p1"]),
            density_b=float(dec["subsampling_fct_p2"]),
            max_input_points=int(cfg["train"]["max_nr_pts"]),
            extra={"imported_from": "depoco reference checkpoint " + Path(yaml_path).parent.name},
        )
    except (KeyError, IndexError, TypeError) as exc:
        raise ModelError(f"{yaml_path}: not a reference configuration ({exc})") from None


def import_reference(ref_dir: Path) -> Autoencoder:
    """Build an Autoencoder from a reference folder (eX.yaml, enc_best.pth, dec_best.pth); weights_only loading."""
    ref_dir = Path(ref_dir)
    yamls = sorted(ref_dir.glob("*.yaml"))
    if not yamls or not (ref_dir / "enc_best.pth").is_file() or not (ref_dir / "dec_best.pth").is_file():
        raise ModelError(f"{ref_dir}: expected eX.yaml, enc_best.pth and dec_best.pth")
    network = Autoencoder(config_from_reference_yaml(yamls[0]))
    state = {}
    for part, fname in (("encoder", "enc_best.pth"), ("decoder", "dec_best.pth")):
        try:
            ref_state = torch.load(ref_dir / fname, map_location="cpu", weights_only=True)
        except Exception as exc:  # torch raises many types for corrupt files
            raise ModelError(f"cannot read {ref_dir / fname}: {str(exc).splitlines()[0]}") from None
        state.update({_reference_key(k, part): v for k, v in ref_state.items()})
    own = network.state_dict()
    for key, value in state.items():
        if key.endswith("kernel_points") and key in own and not torch.allclose(own[key], value, atol=1e-6):
            raise ModelError(f"kernel points of {key} differ from this project's grid layout")
    missing, unexpected = network.load_state_dict(state, strict=False)
    if missing or unexpected:
        raise ModelError(f"reference checkpoint does not match the architecture: missing {missing[:3]}, "
                         f"unexpected {unexpected[:3]}")
    return network
