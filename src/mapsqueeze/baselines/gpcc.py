"""MPEG G-PCC through its reference software `tmc3` (mpeg-pcc-tmc13 with --codingScale), found by
`mapsqueeze.shared.tmc3_executable` ($MAPSQUEEZE_TMC3, PATH, or the shared copy).

Coordinates: tmc3 multiplies PLY positions by --inputScale and truncates toward zero, so we quantise ourselves:
q = round((p - origin) / GRID_STEP_M) with origin the cloud's minimum corner, written as integer-valued float64
PLY properties, and run with --inputScale=1 --srcUnit=1 (metres) --srcUnitLength=GRID_STEP_M (metres per
unit). Octree mode codes cells of edge cell_m (--codingScale = GRID_STEP_M / cell_m); trisoup mode stops the
octree at nodes of 2**node_log2 cells and codes triangles, voxelised back to points by the decoder. The decoder
writes metres relative to the origin (--outputUnitLength=1); `decode` checks that the decoded bounding box
matches the encoded one, which catches a tmc3 that scales differently.

Layout (little-endian): magic b"MSGP", version u8, origin 3 x f64 (metres), input extent 3 x f32 (metres),
bounds tolerance f32 (metres), then the tmc3 bitstream.
"""

import shutil
import struct
import subprocess
import tempfile
from pathlib import Path
from typing import ClassVar

import numpy as np
from plyfile import PlyData, PlyElementParseError, PlyHeaderParseError

from mapsqueeze.baselines.base import BaselineCodec, Setting, setting_number, setting_value
from mapsqueeze.errors import BaselineError, ContainerError
from mapsqueeze.geometry.validation import MAX_ABS_COORDINATE_M, validate_points

GRID_STEP_M = 0.001
"""Input quantisation step (metres) before tmc3 sees the points: 1 mm, far below every coded cell."""
OCTREE_CELLS_M = (0.1, 0.2, 0.4, 0.8)
"""Octree-mode coded cell edges (metres) of the benchmark sweep."""
TRISOUP_CELLS_M = (0.05, 0.1, 0.2)
TRISOUP_NODE_LOG2 = (2, 3, 4, 5)
"""Trisoup-mode sweep: coded cell edges (metres) x triangle node sizes (2**node_log2 cells)."""
DEFAULT_TIMEOUT_S = 600.0

_MAGIC = b"MSGP"
_VERSION = 1
_HEADER = struct.Struct("<4sB3d3ff")
_MODES = ("octree", "trisoup")


class GpccCodec(BaselineCodec):
    """Setting {"mode": "octree", "cell_m": metres} or {"mode": "trisoup", "cell_m": metres, "node_log2": 2..6}."""

    name: ClassVar[str] = "gpcc"
    requirement: ClassVar[str] = ("the MPEG G-PCC reference encoder `tmc3` (a mpeg-pcc-tmc13 with --codingScale): "
                                  "$MAPSQUEEZE_TMC3, on PATH, or shared/tools/tmc3/tmc3")

    def __init__(self, executable: str | None = None, timeout_s: float = DEFAULT_TIMEOUT_S):
        """executable: the tmc3 to run (default: the one `tmc3_executable` finds, else "tmc3")."""
        from mapsqueeze.shared import tmc3_executable

        self.executable = executable or tmc3_executable() or "tmc3"
        self.timeout_s = timeout_s

    def available(self) -> bool:
        return shutil.which(self.executable) is not None

    def settings(self) -> list[Setting]:
        octree = [{"mode": "octree", "cell_m": cell} for cell in OCTREE_CELLS_M]
        trisoup = [
            {"mode": "trisoup", "cell_m": cell, "node_log2": node}
            for cell in TRISOUP_CELLS_M
            for node in TRISOUP_NODE_LOG2
        ]
        return octree + trisoup

    def encoder_arguments(self, setting: Setting, source: Path, bitstream: Path) -> list[str]:
        """tmc3 encoder command-line options for one setting (input PLY in GRID_STEP_M units)."""
        mode = setting_value(setting, "mode", self.name)
        if mode not in _MODES:
            raise BaselineError(f"gpcc: mode must be one of {list(_MODES)}, got {mode!r}")
        cell = setting_number(setting, "cell_m", self.name, GRID_STEP_M, MAX_ABS_COORDINATE_M)
        arguments = [
            "--mode=0",
            f"--uncompressedDataPath={source}",
            f"--compressedStreamPath={bitstream}",
            "--inputScale=1",
            "--srcUnit=1",
            f"--srcUnitLength={GRID_STEP_M!r}",
            "--sequenceScale=1",
            f"--codingScale={GRID_STEP_M / cell!r}",
            "--disableAttributeCoding=1",
            "--mergeDuplicatedPoints=1",
            "--partitionMethod=2",  # tmc3's default slicing (4) corrupts clouds of about 1.1M points or more
        ]
        if mode == "trisoup":
            node_log2 = setting_number(setting, "node_log2", self.name, 2, 6)
            if not node_log2.is_integer():
                raise BaselineError(f"gpcc: node_log2 must be an integer, got {node_log2!r}")
            arguments.append(f"--trisoupNodeSizeLog2={int(node_log2)}")
        return arguments

    def decoder_arguments(self, bitstream: Path, reconstruction: Path) -> list[str]:
        """tmc3 decoder command-line options: binary PLY in metres relative to the encoded origin."""
        return [
            "--mode=1",
            f"--compressedStreamPath={bitstream}",
            f"--reconstructedDataPath={reconstruction}",
            "--outputBinaryPly=1",
            "--outputUnitLength=1",
        ]

    def encode(self, points: np.ndarray, setting: Setting) -> bytes:
        points = validate_points(points)
        origin = points.min(axis=0)
        grid = np.rint((points - origin) / GRID_STEP_M)
        if grid.max() >= 2**31:
            raise BaselineError(f"gpcc: the cloud spans more than {2**31 * GRID_STEP_M:.0f} m")
        with tempfile.TemporaryDirectory(prefix="mapsqueeze-gpcc-") as temp:
            source, bitstream = Path(temp) / "source.ply", Path(temp) / "stream.bin"
            _write_grid_ply(source, grid)
            self._run(self.encoder_arguments(setting, source, bitstream), "encoder")
            if not bitstream.is_file() or bitstream.stat().st_size == 0:
                raise BaselineError("gpcc: tmc3 encoder wrote no bitstream")
            stream = bitstream.read_bytes()
        extent = grid.max(axis=0) * GRID_STEP_M
        header = _HEADER.pack(_MAGIC, _VERSION, *origin, *extent, _bounds_tolerance_m(setting))
        return header + stream

    def decode(self, data: bytes) -> np.ndarray:
        """Decoded points (metres); ContainerError on a bad header, BaselineError when tmc3 fails or mis-scales."""
        data = bytes(data)
        if len(data) <= _HEADER.size:
            raise ContainerError(f"gpcc: {len(data)} bytes is too short for the {_HEADER.size}-byte header + stream")
        magic, version, *values = _HEADER.unpack_from(data)
        if magic != _MAGIC:
            raise ContainerError(f"gpcc: bad magic {magic!r} (expected {_MAGIC!r})")
        if version != _VERSION:
            raise ContainerError(f"gpcc: unsupported version {version} (this build reads {_VERSION})")
        origin, extent, tolerance = np.array(values[:3]), np.array(values[3:6]), values[6]
        if not (np.isfinite(values).all() and np.abs(origin).max() < MAX_ABS_COORDINATE_M and (extent >= 0).all()):
            raise ContainerError(f"gpcc: absurd header values {values}")
        with tempfile.TemporaryDirectory(prefix="mapsqueeze-gpcc-") as temp:
            bitstream, reconstruction = Path(temp) / "stream.bin", Path(temp) / "decoded.ply"
            bitstream.write_bytes(data[_HEADER.size :])
            self._run(self.decoder_arguments(bitstream, reconstruction), "decoder")
            relative = _read_ply_points(reconstruction)
        _check_bounds(relative, extent, tolerance)
        return origin + relative

    def _run(self, arguments: list[str], role: str) -> None:
        try:
            result = subprocess.run(
                [self.executable, *arguments],
                capture_output=True,
                text=True,
                errors="replace",
                timeout=self.timeout_s,
                check=False,
            )
        except FileNotFoundError:
            raise BaselineError(f"gpcc: `{self.executable}` not found; needs {self.requirement}") from None
        except subprocess.TimeoutExpired:
            raise BaselineError(f"gpcc: tmc3 {role} timed out after {self.timeout_s:g} s") from None
        output = result.stdout + result.stderr
        if result.returncode != 0:
            tail = " | ".join(output.strip().splitlines()[-3:])
            raise BaselineError(f"gpcc: tmc3 {role} failed with exit code {result.returncode}: {tail}")
        unknown = [line.strip() for line in output.splitlines() if "Unhandled argument" in line]
        if unknown:
            raise BaselineError(f"gpcc: this tmc3 lacks options the wrapper needs ({'; '.join(unknown)})")


def _bounds_tolerance_m(setting: Setting) -> float:
    """How far (metres) decoded points may stray outside the input bounding box: two coded nodes."""
    node_cells = 2 ** int(setting.get("node_log2", 0)) if setting["mode"] == "trisoup" else 1
    return 2 * float(setting["cell_m"]) * node_cells + GRID_STEP_M


def _write_grid_ply(path: Path, grid: np.ndarray) -> None:
    """Binary PLY of integer-valued coordinates; tmc3 reads x, y, z only as `float`/`float32`/`float64`."""
    header = (
        "ply\nformat binary_little_endian 1.0\n"
        f"element vertex {len(grid)}\n"
        "property float64 x\nproperty float64 y\nproperty float64 z\nend_header\n"
    )
    path.write_bytes(header.encode("ascii") + np.ascontiguousarray(grid, dtype="<f8").tobytes())


def _read_ply_points(path: Path) -> np.ndarray:
    if not path.is_file():
        raise BaselineError("gpcc: tmc3 decoder wrote no point cloud")
    try:
        vertex = PlyData.read(str(path))["vertex"]
        points = np.stack([np.asarray(vertex[axis], dtype=np.float64) for axis in "xyz"], axis=1)
    except (PlyHeaderParseError, PlyElementParseError, KeyError, ValueError) as exc:
        raise BaselineError(f"gpcc: cannot read tmc3's decoded PLY ({exc})") from None
    if len(points) == 0:
        raise BaselineError("gpcc: tmc3 decoded an empty point cloud")
    return points


def _check_bounds(relative: np.ndarray, extent: np.ndarray, tolerance: float) -> None:
    """Decoded points (metres from the origin) must fill the encoded box [0, extent] up to `tolerance`."""
    low, high = relative.min(axis=0), relative.max(axis=0)
    inside = (low >= -tolerance).all() and (high <= extent + tolerance).all()
    spread = float(np.ptp(relative, axis=0).max()) >= float(extent.max()) / 2 - tolerance
    if not (inside and spread):
        raise BaselineError(
            f"gpcc: decoded bounding box {low.round(3).tolist()}..{high.round(3).tolist()} m does not match the "
            f"encoded 0..{extent.round(3).tolist()} m (tolerance {tolerance:.3f} m): tmc3 scaled the output differently"
        )
