"""Where the material shared beside the project lives: real LiDAR data, the reference checkpoints, the G-PCC encoder.

One resolver for every caller (demo, bench, baselines, tests, scripts in benchmarks/). The folder is
`$MAPSQUEEZE_SHARED` when set; otherwise the `shared` folder beside the repository root of a source checkout
(found from this file's location), else `../shared` from the working directory. Imports only the standard library.
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path

SHARED_ENV = "MAPSQUEEZE_SHARED"
"""Environment variable naming the shared folder (overrides every default)."""
TMC3_ENV = "MAPSQUEEZE_TMC3"
"""Environment variable naming the MPEG G-PCC encoder `tmc3` (overrides PATH and the shared copy)."""

_SOURCE_ROOT = Path(__file__).resolve().parents[2]  # src/mapsqueeze/shared.py -> the repository root


def shared_dir() -> Path:
    """The shared folder (it may not exist: callers check the files they need)."""
    override = os.environ.get(SHARED_ENV)
    if override:
        return Path(override).expanduser()
    beside_checkout = _SOURCE_ROOT.parent / "shared"
    if (_SOURCE_ROOT / "pyproject.toml").is_file() and beside_checkout.is_dir():
        return beside_checkout
    return Path.cwd().parent / "shared"


def real_data_dir() -> Path:
    """Real scans and sweeps: kitti_seq00_scans/, a nuScenes .pcd.bin, submaps/."""
    return shared_dir() / "data" / "real"


def real_submaps_dir() -> Path:
    """Real 40 m submaps (PLY, metres around the sensor), among them kitti_hdl64_6scans.ply."""
    return real_data_dir() / "submaps"


def reference_checkpoints_dir() -> Path:
    """The reference implementation's released checkpoints: e0..e3/ and golden/ outputs."""
    return shared_dir() / "reference" / "depoco"


def tmc3_executable() -> str | None:
    """The MPEG G-PCC encoder: `$MAPSQUEEZE_TMC3`, else `tmc3` on PATH, else the shared copy; None when absent."""
    override = os.environ.get(TMC3_ENV)
    if override:
        return override
    on_path = shutil.which("tmc3")
    if on_path:
        return on_path
    shared_copy = shared_dir() / "tools" / "tmc3" / "tmc3"
    return str(shared_copy) if os.access(shared_copy, os.X_OK) else None
