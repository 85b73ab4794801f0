"""`mapsqueeze view`: one self-contained HTML page of a .msq file's decoded map, optionally over its original
(colour by height, intensity or error, tile grid and modes, embedding points, summary). See docs/viewer.md."""

from __future__ import annotations

import os
from pathlib import Path

from mapsqueeze.view.page import render_page
from mapsqueeze.view.scene import DEFAULT_MAX_POINTS, INTENSITY_ATTRIBUTES, CloudInput, ViewInput, build_scene

__all__ = ["DEFAULT_MAX_POINTS", "INTENSITY_ATTRIBUTES", "CloudInput", "ViewInput", "build_scene", "load_cloud",
           "render_page", "write_view"]


def load_cloud(path: str | os.PathLike) -> CloudInput:
    """A point-cloud file's points and, when it stores them, intensities (any format `mapsqueeze.io` reads)."""
    from mapsqueeze.io import read_point_cloud

    return CloudInput.from_point_cloud(read_point_cloud(path))


def write_view(view: ViewInput, output: str | os.PathLike, max_points: int = DEFAULT_MAX_POINTS) -> dict:
    """Build the page of `view` and write it to `output` atomically; returns the scene (its counts and summary)."""
    from mapsqueeze.io import atomic_write_bytes

    scene = build_scene(view, max_points)
    atomic_write_bytes(Path(output), render_page(scene).encode("utf-8"))
    return scene
