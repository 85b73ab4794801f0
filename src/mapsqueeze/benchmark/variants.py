"""The (codec, setting) pairs a benchmark runs: the learned codecs through the same `mapsqueeze.compress` /
`mapsqueeze.decompress` calls as the CLI, and every classical codec of the baselines registry."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mapsqueeze.errors import MapsqueezeError

LEARNED_CODECS = ("mapsqueeze", "depoco-ref")
"""Codecs outside the baselines registry: the shipped (or given) models, and the reference checkpoints."""


@dataclass
class Variant:
    """One codec at one setting: encode(points, origin) -> bytes, decode(bytes, origin) -> world points (metres)."""

    codec: str
    setting: str
    weights: str
    """SHA-256 of the model's weights ("" for a classical codec)."""
    encode: Callable[[np.ndarray, np.ndarray], bytes]
    decode: Callable[[bytes, np.ndarray], np.ndarray]

    def key(self) -> tuple[str, str]:
        return self.codec, self.setting


def known_codecs() -> tuple[str, ...]:
    """Every codec name `build_variants` accepts."""
    from mapsqueeze.baselines import BASELINES

    return (*LEARNED_CODECS, *BASELINES)


def _learned_variants(codec: str, models: dict[str, object], precision: str, refine_steps: int = 0
                      ) -> list[Variant]:
    """One variant per model; with refine_steps the setting reads e.g. "e1,q+refine20"."""
    from mapsqueeze.api import compress, decompress

    label = f"{precision}+refine{refine_steps}" if refine_steps else precision
    return [Variant(codec, f"{name},{label}", model.weights_sha256,
                    lambda pts, origin, m=model: compress(pts, model=m, precision=precision, refine_steps=refine_steps),
                    lambda data, origin, m=model: decompress(data, model=m))
            for name, model in models.items()]


def state_sha256(network) -> str:
    """SHA-256 of a network's tensors (identifies an in-memory model such as an imported reference)."""
    import hashlib

    digest = hashlib.sha256()
    for key, value in sorted(network.state_dict().items()):
        digest.update(key.encode())
        digest.update(value.detach().cpu().contiguous().numpy().tobytes())
    return digest.hexdigest()


def unique_labels(names: list[str]) -> list[str]:
    """Shortest path suffixes that tell the models apart: runs/a/best, runs/b/best -> a/best, b/best (a training
    run's generic best/ or last/ folder always keeps its run's name)."""
    parts = [Path(n).parts or (n,) for n in names]
    depth = 2 if any(p[-1] in ("best", "last") and len(p) > 1 for p in parts) else 1
    while depth < max(map(len, parts)) and len({p[-depth:] for p in parts}) < len(parts):
        depth += 1
    return ["/".join(p[-depth:]) for p in parts]


def _reference_models(log: Callable[[str], None], device: str = "cpu") -> dict[str, object]:
    """The reference checkpoints (e0..e3 found in the shared folder), imported to run on `device` (a checked name);
    {} with a message when absent."""
    from mapsqueeze.model import import_reference
    from mapsqueeze.model import CompressionModel
    from mapsqueeze.shared import reference_checkpoints_dir

    reference_dir = reference_checkpoints_dir()
    refs = sorted(p for p in reference_dir.glob("e[0-3]") if (p / "enc_best.pth").is_file())
    if not refs:
        log(f"depoco-ref: reference checkpoints not found in {reference_dir} (skipped)")
    loaded = {}
    for p in refs:
        network = import_reference(p)
        loaded[p.name] = CompressionModel.from_network(network, f"depoco-{p.name}", state_sha256(network), device)
    return loaded


def _baseline_variants(codec: str, log: Callable[[str], None]) -> list[Variant]:
    """Every setting of the sweep of a registered classical codec ([] with a message when unavailable). Classical
    codecs code the cloud relative to its lower corner, as a file of local coordinates would be."""
    from mapsqueeze.baselines import get_baseline, setting_label

    baseline = get_baseline(codec)
    if not baseline.available():
        log(f"{codec}: unavailable ({baseline.requirement}) (skipped)")
        return []
    return [Variant(codec, setting_label(setting), "",
                    lambda pts, origin, s=setting: baseline.encode(pts - origin, s),
                    lambda data, origin: baseline.decode(data) + origin)
            for setting in baseline.settings()]


def build_variants(codecs: list[str], models: list[str], precision: str, log: Callable[[str], None],
                   refine: tuple[int, ...] = (0,), device: str = "cpu") -> list[Variant]:
    """Every (codec, setting) to run; unavailable codecs are skipped with a message. The learned codecs run at each
    number of encode-time refinement steps in `refine` (depoco-ref's paper-mode f16 only without refinement), their
    networks on `device` (MapsqueezeError first for one this machine lacks, `model.devices.device_name`)."""
    from mapsqueeze.model import load_model, shipped_models
    from mapsqueeze.model.devices import device_name

    unknown = [c for c in codecs if c not in known_codecs()]
    if unknown:
        raise MapsqueezeError(f"unknown codec {unknown[0]!r} (known: {', '.join(known_codecs())})")
    device = device_name(device)
    variants: list[Variant] = []
    for codec in codecs:
        if codec == "mapsqueeze":
            names = models or shipped_models()
            if not names:
                log("mapsqueeze: no shipped model; pass --models DIR,... (skipped)")
            loaded = dict(zip(unique_labels(names), (load_model(name, device) for name in names)))
            for steps in refine:
                variants += _learned_variants(codec, loaded, precision, steps)
        elif codec == "depoco-ref":
            loaded = _reference_models(log, device)
            # the paper's float16 embeddings, and the same networks through our entropy-coded embeddings
            if 0 in refine:
                for ref_precision in dict.fromkeys(("f16", precision)):
                    variants += _learned_variants(codec, loaded, ref_precision)
            for steps in refine:
                if steps:
                    variants += _learned_variants(codec, loaded, precision, steps)
        else:
            variants += _baseline_variants(codec, log)
    return variants
