"""A stand-in for a GPU on a machine without one: tensors on torch's "meta" device that hold real CPU values.

Inside `simulated_device()`, every tensor placed on "meta" (`.to("meta")`, a factory given device="meta", a module
moved there) is an `OnDevice` wrapping a CPU tensor, so the code computes real values while taking the branches it
takes on a GPU (`device.type != "cpu"`). What CUDA refuses is refused: an operation mixing an `OnDevice` tensor with
a CPU tensor that is not 0-dimensional (CUDA takes those, CPU indices of `tensor[indices]` and a CPU source of
`copy_`, nothing else), and `.numpy()` or `np.asarray` of an `OnDevice` tensor (CUDA's need `.cpu()` first).
Inside the block `devices.torch_device` takes "meta" as a device the network runs on, as it takes "cuda".
Not simulated: other threads (torch's dispatch modes hold in the thread that enters them), torch.load with
map_location on the device, process groups (nccl), CUDA's own rounding and memory.
"""

from __future__ import annotations

import contextlib

import torch
from torch.utils._python_dispatch import TorchDispatchMode
from torch.utils._pytree import tree_flatten, tree_map

DEVICE = "meta"
_CPU = torch.device("cpu")
_COPY = torch.ops.aten._to_copy.default
_CROSS_DEVICE = {torch.ops.aten.copy_.default}  # device_tensor.copy_(cpu_tensor) works on CUDA
_CPU_INDICES_ALLOWED = {torch.ops.aten.index.Tensor}  # cuda_tensor[cpu_indices] works on CUDA


class OnDevice(torch.Tensor):
    """A tensor on the simulated device: device "meta" to torch, the values in `elem` (CPU)."""

    elem: torch.Tensor

    @staticmethod
    def __new__(cls, elem: torch.Tensor):
        wrapper = torch.Tensor._make_wrapper_subclass(cls, elem.shape, strides=elem.stride(), dtype=elem.dtype,
                                                      device=torch.device(DEVICE), requires_grad=elem.requires_grad)
        wrapper.elem = elem
        return wrapper

    @classmethod
    def __torch_dispatch__(cls, func, types, args=(), kwargs=None):
        return NotImplemented  # only inside `_Simulation`

    @property
    def is_meta(self) -> bool:
        return False  # it holds values: load_state_dict copies into it

    def __reduce_ex__(self, protocol):
        return self.elem.__reduce_ex__(protocol)  # torch.save writes the values, as it copies a GPU's to the file

    def __repr__(self):
        return f"OnDevice({self.elem!r})"


def _device_of(kwargs: dict) -> torch.device | None:
    device = kwargs.get("device")
    return None if device is None else torch.device(device)


class _Simulation(TorchDispatchMode):
    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        kwargs = dict(kwargs or {})
        flat, _ = tree_flatten((args, kwargs))
        on_device = any(isinstance(t, OnDevice) for t in flat)
        target = _device_of(kwargs)
        to_device = target is not None and target.type == DEVICE
        if to_device:
            kwargs["device"] = _CPU
        if on_device and not (func is _COPY and target is not None) and func not in _CROSS_DEVICE:
            cpu = [t for t in flat if type(t) is torch.Tensor and t.dim() > 0]
            if func in _CPU_INDICES_ALLOWED:
                cpu = [t for t in cpu if t is args[0]]
            if cpu:
                raise RuntimeError(f"Expected all tensors to be on the same device: {func} was given CPU tensors "
                                   f"of shapes {[tuple(t.shape) for t in cpu]} with tensors on the device")
        out = func(*tree_map(lambda t: t.elem if isinstance(t, OnDevice) else t, args),
                   **tree_map(lambda t: t.elem if isinstance(t, OnDevice) else t, kwargs))
        if target is not None and target.type == "cpu":
            return out
        if on_device or to_device:
            return tree_map(lambda t: OnDevice(t) if type(t) is torch.Tensor else t, out)
        return out


@contextlib.contextmanager
def simulated_device():
    """The block runs with DEVICE simulating a GPU (see the module's docstring)."""
    from mapsqueeze.model import devices

    types = devices.DEVICE_TYPES
    devices.DEVICE_TYPES = (*types, DEVICE)
    try:
        with _Simulation():
            yield DEVICE
    finally:
        devices.DEVICE_TYPES = types
