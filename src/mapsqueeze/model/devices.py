"""The torch device a device name gives (`train --device`, `compress --device`, `load_model(device=...)`), checked
before any work; torch is imported only for a name other than "cpu"."""

from __future__ import annotations

import os

from mapsqueeze.errors import MapsqueezeError

DEVICE_TYPES = ("cpu", "cuda")
"""The kinds of device the network runs on (torch knows others: mps, xpu, meta, ..., which it does not)."""
CUBLAS_WORKSPACE = ":4096:8"
"""cuBLAS workspace with which its matrix products give the same bits every run (CUBLAS_WORKSPACE_CONFIG), the setting
torch's deterministic mode (`refinetorch`) asks for; torch reads it once, at the process's first matrix product."""


def torch_device(name: str, processes: int = 1) -> torch.device:
    """torch.device of `name` ("cpu", "cuda", "cuda:1", ...). MapsqueezeError for a name torch does not know or of a
    type not in DEVICE_TYPES, and for cuda where this torch has no CUDA or sees no GPU, where the GPU of the index is
    absent, or where `processes` (one GPU each, from cuda:0) outnumber the GPUs. For cuda, sets CUBLAS_WORKSPACE_CONFIG to `CUBLAS_WORKSPACE`
    unless it is set."""
    import torch

    try:
        device = torch.device(name)
    except (RuntimeError, TypeError):
        raise MapsqueezeError(f"unknown device {name!r}: use cpu or cuda (cuda:N for the GPU of index N)") from None
    if device.type not in DEVICE_TYPES:
        raise MapsqueezeError(f"device {name!r} is not supported: use cpu or cuda (cuda:N for the GPU of index N)")
    if device.type != "cuda":
        return device
    if not torch.cuda.is_available():
        reason = "this torch is built without CUDA" if torch.version.cuda is None else "it sees no GPU"
        raise MapsqueezeError(f"device {name!r} is not available: {reason} (torch {torch.__version__})")
    count = torch.cuda.device_count()
    if device.index is not None and device.index >= count:
        raise MapsqueezeError(f"device {name!r} is not available: {count} GPU(s), indices 0 to {count - 1}")
    if processes > count:
        raise MapsqueezeError(f"{processes} processes on {name!r} need {processes} GPUs (one each), {count} found")
    os.environ.setdefault("CUBLAS_WORKSPACE_CONFIG", CUBLAS_WORKSPACE)
    return device


def device_name(name: str) -> str:
    """The name of a checked device (`torch_device`), as torch writes it ("cpu", "cuda", "cuda:1"): "cpu" for any
    name of the CPU; "cpu" itself imports no torch."""
    if str(name) == "cpu":
        return "cpu"
    device = torch_device(str(name))
    return "cpu" if device.type == "cpu" else str(device)


def same_device(first: str, second: str) -> bool:
    """Whether two checked device names (`device_name`) name one device: "cuda" is the current GPU
    (torch.cuda.current_device()), so "cuda" and "cuda:0" are one where GPU 0 is current."""
    if first == second:
        return True
    if "cpu" in (first, second):
        return False
    import torch

    def resolved(name: str) -> torch.device:
        device = torch.device(name)
        return torch.device("cuda", torch.cuda.current_device()) if device.index is None else device

    return resolved(first) == resolved(second)
