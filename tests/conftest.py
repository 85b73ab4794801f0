"""Shared fixtures: the shared material (real data, reference checkpoints, tmc3) through mapsqueeze.shared.

Missing material skips the tests that need it, or fails them when MAPSQUEEZE_REQUIRE_SHARED=1 (as in CI), so a
clone without the shared folder cannot pass its reference tests silently.
"""

import os
from pathlib import Path

import pytest

from mapsqueeze.shared import SHARED_ENV, real_data_dir, real_submaps_dir, reference_checkpoints_dir, tmc3_executable

REQUIRE_SHARED_ENV = "MAPSQUEEZE_REQUIRE_SHARED"


def missing_shared(what: str) -> None:
    """Skip the calling test because `what` is absent, or fail it when the shared material is required."""
    message = f"{what} absent (set {SHARED_ENV} to the shared folder)"
    if os.environ.get(REQUIRE_SHARED_ENV) == "1":
        pytest.fail(f"{message}; {REQUIRE_SHARED_ENV}=1 requires it")
    pytest.skip(message)


@pytest.fixture
def shared_file():
    """shared_file(path) -> path when it exists, else skip (or fail when the shared material is required)."""

    def require(path: Path) -> Path:
        if not path.exists():
            missing_shared(str(path))
        return path

    return require


@pytest.fixture
def real_data(shared_file):
    """Folder of the real scans and submaps (shared/data/real)."""
    return shared_file(real_data_dir())


@pytest.fixture
def reference_dir(shared_file):
    """Folder of the reference checkpoints (e0..e3, golden/)."""
    shared_file(reference_checkpoints_dir() / "e0" / "enc_best.pth")
    return reference_checkpoints_dir()


@pytest.fixture
def real_submaps(shared_file):
    """Folder of the real 40 m submaps."""
    return shared_file(real_submaps_dir())


@pytest.fixture
def kitti_submap(shared_file):
    """The real KITTI submap of six HDL-64E scans (101,924 points)."""
    return shared_file(real_submaps_dir() / "kitti_hdl64_6scans.ply")


@pytest.fixture
def tmc3():
    """Path of the real MPEG G-PCC encoder `tmc3`."""
    executable = tmc3_executable()
    if executable is None:
        missing_shared("the MPEG G-PCC encoder tmc3")
    return executable


@pytest.fixture
def run_cli(monkeypatch, capsys):
    """Run the `mapsqueeze` entry point in-process: run_cli(*args) -> (exit code, stdout, stderr)."""
    import sys

    from mapsqueeze.cli import main

    def run(*args: str) -> tuple[int, str, str]:
        monkeypatch.setattr(sys, "argv", ["mapsqueeze", *args])
        with pytest.raises(SystemExit) as exit_info:
            main()
        captured = capsys.readouterr()
        return exit_info.value.code, captured.out, captured.err

    return run


@pytest.fixture(scope="session")
def tiny_model_dir(tmp_path_factory):
    """A small randomly initialised model (8 x 8 x 4 m tiles, r_s = 2 m) saved to a folder: fast to run, and the
    codec does not care whether the weights are trained."""
    from mapsqueeze.model import ModelConfig, build_model, save_model

    config = ModelConfig.for_rate("e1", tile_size=(8.0, 8.0, 4.0), map_size=8.0, max_input_points=2000)
    return save_model(build_model(config, seed=1), tmp_path_factory.mktemp("model") / "tiny")


def _lzf_compress(data: bytes) -> bytes:
    """A greedy LZF encoder (liblzf's stream format, a dict of 3-byte prefixes instead of its hash table): literal
    runs of up to 32 bytes and back-references of 3 to 264 bytes up to 8,192 bytes back, overlapping ones included.
    Tests only; slow (~1 s a megabyte)."""
    out, literal, last = bytearray(), bytearray(), {}

    def flush() -> None:
        for first in range(0, len(literal), 32):
            run = literal[first : first + 32]
            out.append(len(run) - 1)
            out.extend(run)
        literal.clear()

    position = 0
    while position < len(data):
        key = data[position : position + 3]
        ref = last.get(key) if len(key) == 3 else None
        last[key] = position
        if ref is None or position - ref > 8192:
            literal.append(data[position])
            position += 1
            continue
        length, limit = 3, min(264, len(data) - position)
        while length < limit and data[ref + length] == data[position + length]:
            length += 1
        flush()
        distance = position - ref - 1
        if length - 2 < 7:
            out.append(((length - 2) << 5) | (distance >> 8))
        else:
            out.extend((0xE0 | (distance >> 8), length - 9))
        out.append(distance & 0xFF)
        position += length
    flush()
    return bytes(out)


def _binary_compressed_pcd(path: Path, records, height: int = 1) -> Path:
    """Write a structured array (a subarray field: COUNT > 1) as a DATA binary_compressed PCD of `height` rows: the
    fields in turn, LZF-compressed."""
    import numpy as np

    names = records.dtype.names
    kinds = [records.dtype[name].base for name in names]
    header = (f"VERSION 0.7\nFIELDS {' '.join(names)}\n"
              f"SIZE {' '.join(str(kind.itemsize) for kind in kinds)}\n"
              f"TYPE {' '.join(kind.kind.upper() for kind in kinds)}\n"
              f"COUNT {' '.join(str(int(np.prod(records.dtype[name].shape))) for name in names)}\n"
              f"WIDTH {len(records) // height}\nHEIGHT {height}\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {len(records)}\n"
              "DATA binary_compressed\n")
    block = b"".join(np.ascontiguousarray(records[name]).tobytes() for name in names)
    compressed = _lzf_compress(block)
    path.write_bytes(header.encode() + len(compressed).to_bytes(4, "little") + len(block).to_bytes(4, "little")
                     + compressed)
    return path


@pytest.fixture
def lzf_compress():
    """lzf_compress(data) -> an LZF stream of data (a greedy encoder of the tests)."""
    return _lzf_compress


@pytest.fixture
def binary_compressed_pcd():
    """binary_compressed_pcd(path, records, height=1) -> path, records written as a DATA binary_compressed PCD."""
    return _binary_compressed_pcd
