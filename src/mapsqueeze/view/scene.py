"""What the viewer page shows, computed from the API's results: the decoded map and the original as evenly spread,
coarse-to-fine ordered subsets with their heights, intensities and nearest-neighbour errors, the tiles with their
coding modes and embedding points, and the summary metrics.

Positions, errors and intensities travel as little-endian uint16 arrays (base64 in the page): positions in steps of
the scene box / 65535 per axis (0.6 mm over a 40 m tile, 3 cm over 2 km), errors in steps of the largest drawn
error / 65535.
"""

from __future__ import annotations

import base64
import os
from dataclasses import dataclass

import numpy as np

from mapsqueeze import api
from mapsqueeze.codec.container import DEFAULT_MAX_TILE_POINTS
from mapsqueeze.geometry.morton import coarse_to_fine_subset
from mapsqueeze.io import PointCloud
from mapsqueeze.metrics import Metrics, evaluate, nearest_distances

DEFAULT_MAX_POINTS = 500_000
"""Points drawn per cloud by default (the page holds about 10 bytes per point, 13 in base64)."""
QUANT_STEPS = 65535
HEIGHT_PERCENTILES = (1.0, 99.0)
"""The height colour ramp spans these percentiles of the drawn heights (outliers saturate)."""
ERROR_PERCENTILE = 95.0
"""The error colour bar starts at this percentile of the drawn errors (adjustable in the page)."""
INTENSITY_ATTRIBUTES = ("intensity", "reflectance")
"""Attribute names read as the intensity (LAS, PLY, PCD; KITTI .bin calls it reflectance)."""


@dataclass
class CloudInput:
    """A point cloud to show: (N, 3) float64 world metres and, when it has them, (N,) intensities;
    nan_points_dropped: the points of its file left out for a NaN coordinate (`PointCloud.nan_points_dropped`)."""

    points: np.ndarray
    intensity: np.ndarray | None = None
    nan_points_dropped: int = 0

    @classmethod
    def from_point_cloud(cls, cloud: PointCloud) -> CloudInput:
        """A PointCloud's points and its first attribute named in INTENSITY_ATTRIBUTES (as float64), if any."""
        intensity = next((cloud.attributes[name] for name in INTENSITY_ATTRIBUTES if name in cloud.attributes), None)
        return cls(cloud.points, None if intensity is None else np.asarray(intensity, dtype=np.float64),
                   cloud.nan_points_dropped)


@dataclass
class ViewInput:
    """Everything the page is built from; `build_scene` fills what is not given."""

    name: str
    msq: bytes | str | os.PathLike
    original: CloudInput | None = None
    decoded: CloudInput | None = None  # default: api.decompress_cloud(msq) at the stored counts, with its intensity
    metrics: Metrics | None = None  # default: evaluate(original, decoded) when the original is given
    model: object = None  # decoding model (default: the one named in the file)
    device: str = "cpu"  # where a model given by name, or the file's, decodes (`api.decompress_cloud`)
    max_tile_points: int = DEFAULT_MAX_TILE_POINTS  # the decoder's guard (`api.decompress_cloud`)


def _b64(array: np.ndarray, dtype: str) -> str:
    return base64.b64encode(np.ascontiguousarray(array, dtype=dtype).tobytes()).decode("ascii")


def _quantise_unit(values: np.ndarray, low: float, span: float) -> np.ndarray:
    scale = QUANT_STEPS / span if span > 0 else 0.0
    return np.clip(np.rint((values - low) * scale), 0, QUANT_STEPS).astype("<u2")


def _metric_or_none(metrics: Metrics | None, name: str) -> float | None:
    return None if metrics is None else float(getattr(metrics, name))


def build_scene(view: ViewInput, max_points: int = DEFAULT_MAX_POINTS) -> dict:
    """The page's data (a JSON-serialisable dict) of a .msq file, its decoded map and optionally its original.

    The decoded map's intensities are those coded in the file (none for a geometry-only file); intensity colouring
    is offered only when the decoded map has them. Each cloud keeps `coarse_to_fine_subset(points, max_points)`: an
    evenly spread subset whose every prefix is evenly spread too, so the page draws a prefix while the camera moves.
    Errors are each drawn point's distance to the nearest point of the whole other cloud (metres).
    """
    if max_points < 1:
        raise ValueError(f"max_points must be at least 1, got {max_points}")
    summary = api.info(view.msq)
    tile_list = api.tiles(view.msq)
    decoded = view.decoded or CloudInput.from_point_cloud(api.decompress_cloud(
        view.msq, model=view.model, device=view.device, max_tile_points=view.max_tile_points))
    metrics = view.metrics
    if metrics is None and view.original is not None:
        metrics = evaluate(view.original.points, decoded.points, n_bytes=summary.file_bytes)
    clouds = [("original", view.original), ("decoded", decoded)]
    clouds = [(name, cloud) for name, cloud in clouds if cloud is not None]
    drawn = {name: coarse_to_fine_subset(cloud.points, max_points) for name, cloud in clouds}
    embedding = np.concatenate([t.embedding for t in tile_list])
    everything = np.concatenate([cloud.points[drawn[name]] for name, cloud in clouds] + [embedding])
    low, high = everything.min(axis=0), everything.max(axis=0)
    centre = np.round((low + high) / 2, 3)
    size = np.maximum(high - low, 1e-6)

    def positions(points: np.ndarray) -> str:
        quantised = np.stack([_quantise_unit(points[:, a], low[a], size[a]) for a in range(3)], axis=1)
        return _b64(quantised, "<u2")

    errors = {}
    if view.original is not None:
        others = {"original": decoded.points, "decoded": view.original.points}
        errors = {name: nearest_distances(cloud.points[drawn[name]], others[name]) for name, cloud in clouds}
    error_max = max((float(e.max()) for e in errors.values() if len(e)), default=0.0)
    show_intensity = decoded.intensity is not None
    intensities = [cloud.intensity[drawn[name]] for name, cloud in clouds
                   if show_intensity and cloud.intensity is not None]
    intensity_range = ([float(min(i.min() for i in intensities)), float(max(i.max() for i in intensities))]
                       if intensities else None)
    heights = np.concatenate([cloud.points[drawn[name], 2] for name, cloud in clouds])
    payload_clouds = []
    for name, cloud in clouds:
        points = cloud.points[drawn[name]]
        entry = {"name": name, "total": int(len(cloud.points)), "drawn": int(len(points)),
                 "positions": positions(points), "error": None, "intensity": None}
        if name in errors:
            entry["error"] = _b64(_quantise_unit(errors[name], 0.0, error_max), "<u2")
        if intensity_range is not None and cloud.intensity is not None:
            span = intensity_range[1] - intensity_range[0]
            entry["intensity"] = _b64(_quantise_unit(cloud.intensity[drawn[name]], intensity_range[0], span), "<u2")
        payload_clouds.append(entry)
    all_errors = np.concatenate(list(errors.values())) if errors else np.zeros(0)
    return {
        "name": view.name,
        "centre": centre.tolist(),  # world coordinates of the scene's (0, 0, 0)
        "box": {"low": (low - centre).tolist(), "size": size.tolist()},
        "clouds": payload_clouds,
        "embedding": {"count": int(len(embedding)), "positions": positions(embedding)},
        "heightRange": [float(v - centre[2]) for v in np.percentile(heights, HEIGHT_PERCENTILES)],
        "errorMax": error_max,
        "errorDefault": float(np.percentile(all_errors, ERROR_PERCENTILE)) if len(all_errors) else 0.0,
        "intensityRange": intensity_range,
        "tiles": [{"index": list(t.index), "coding": t.coding, "model": t.model_id, "points": t.n_points,
                   "bytes": t.payload_bytes, "embedding": int(len(t.embedding)),
                   "low": (t.cell[0] - centre).tolist(), "high": (t.cell[1] - centre).tolist()}
                  for t in tile_list],
        "summary": {
            "model": summary.model_id, "precision": summary.precision, "fileBytes": summary.file_bytes,
            "points": summary.n_points, "decoded": int(len(decoded.points)),
            "original": None if view.original is None else int(len(view.original.points)),
            "bpp": 8.0 * summary.file_bytes / (len(view.original.points) if view.original is not None
                                               else summary.n_points),
            "dE": _metric_or_none(metrics, "d_e"), "dPerp": _metric_or_none(metrics, "d_perp"),
            "iou": _metric_or_none(metrics, "iou"), "tileSize": list(summary.tile_size),
        },
    }
