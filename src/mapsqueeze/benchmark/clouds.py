"""The clouds a benchmark runs on: dataset splits, folders of cloud files, single files."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np


@dataclass
class Cloud:
    name: str
    points: np.ndarray  # (N, 3) float64 world metres
    origin: np.ndarray  # lower corner of its box (metres): mapsqueeze tiles start here


def collect_clouds(inputs: list[Path], split: str = "test", every: int = 1) -> Iterator[Cloud]:
    """Clouds from dataset folders (the given split), plain folders (every cloud file) and single files; with
    every=N only the first, (N+1)-th, ... of them (the others are not read)."""
    from mapsqueeze.data.mapping import MANIFEST_NAME, read_dataset
    from mapsqueeze.io import point_cloud_files, read_points

    def sources() -> Iterator[tuple[str, Callable[[], tuple[np.ndarray, np.ndarray]]]]:
        """(name, loader of (points, origin)) of every cloud, nothing read yet."""
        for path in inputs:
            if (path / MANIFEST_NAME).is_file():
                for record in read_dataset(path).split(split):
                    yield f"{path.name}/{record.path.stem}", lambda r=record: (r.load().points, r.bounds[0])
            else:
                files = point_cloud_files(path) if path.is_dir() else [path]
                for file in files:
                    yield file.stem, lambda f=file: _points_and_corner(read_points(f))

    for position, (name, load) in enumerate(sources()):
        if position % every == 0:
            yield Cloud(name, *load())


def _points_and_corner(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return points, points.min(axis=0)
