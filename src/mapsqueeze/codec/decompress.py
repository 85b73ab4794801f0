""".msq -> points: read the header and tile table, decode the selected tiles one at a time, place them in the world."""

from __future__ import annotations

import os
import sys
from collections.abc import Iterator, Sequence

import numpy as np

from mapsqueeze.codec.attributes import decode_tile_attributes, with_constants
from mapsqueeze.codec.attrlegacy import decode_legacy_tile_attributes
from mapsqueeze.codec.container import (
    ATTRIBUTES_ON_DECODED_GEOMETRY,
    DEFAULT_MAX_TILE_POINTS,
    MAX_POINTS_PER_TILE,
    SUPPORT_CRC_VERSION,
    ContainerReader,
    TileCoding,
    TileEntry,
    frame_origin,
    open_container,
)
from mapsqueeze.codec.executor import ProgressCallback, open_executor
from mapsqueeze.codec.header import DefaultCount, Header
from mapsqueeze.codec.octreetile import decode_octree_tile
from mapsqueeze.codec.postfilter import PostFilter, decode_patch_choices, split_patch_choices
from mapsqueeze.codec.rawtile import decode_raw_tile
from mapsqueeze.codec.seams import InternalFace, internal_faces, thin_at_faces
from mapsqueeze.codec.tilepoints import network_points, octree_points
from mapsqueeze.errors import ContainerError, DecodeLimitError, InvalidPointCloudError, MapsqueezeError, ModelError
from mapsqueeze.geometry.resample import resample_to_count
from mapsqueeze.io import PointCloud

MIN_DENSITY_EXTENT_M = 1.0
"""--density counts points per cubic metre of each tile's point bounding box, each side at least this long."""


def parse_bbox(bbox: Sequence[float]) -> np.ndarray:
    """(2, 3) float64 [[x0, y0, z0], [x1, y1, z1]] from six numbers, lower corner first."""
    try:
        box = np.asarray(bbox, dtype=np.float64)
    except (TypeError, ValueError):
        box = np.empty(0)
    if box.shape != (6,) or not np.isfinite(box).all() or (box[:3] > box[3:]).any():
        shown = (",".join(np.format_float_positional(v, trim="-") for v in box) if box.shape == (6,)
                 else repr(bbox))
        raise InvalidPointCloudError(f"bbox must be six finite numbers x0,y0,z0,x1,y1,z1 with x0<=x1, y0<=y1, "
                                     f"z0<=z1, got {shown}")
    return box.reshape(2, 3)


def tile_origin(header: Header, entry: TileEntry) -> np.ndarray:
    """float64 world lower corner of a tile (the same arithmetic as geometry.tiling)."""
    return np.asarray(header.origin) + np.asarray(entry.index, dtype=np.int64) * np.asarray(header.tile_size)


def tile_frame(header: Header, entry: TileEntry) -> np.ndarray:
    """float64 world origin of the coordinates a tile's payload decodes to (`container.frame_origin`)."""
    return frame_origin(tile_origin(header, entry), entry.bounds_lo, np.asarray(header.tile_size))


def tile_world_bounds(header: Header, entry: TileEntry) -> np.ndarray:
    """(2, 3) float64 world box of the tile's input points."""
    return tile_origin(header, entry) + entry.bounds_m(np.asarray(header.tile_size))


def target_counts(header: Header, entries: list[TileEntry], density: float | None, n_points: int | None,
                  max_tile_points: int = DEFAULT_MAX_TILE_POINTS) -> list[int | None]:
    """Points to decode per tile: `density` per m^3 of each tile's box, `n_points` in all (split in proportion to
    the stored counts, largest remainders first), or else the file's default: the stored counts, or None (the
    native count of each tile's coding) when the header's default count is native. A count above
    `max_tile_points` (at most MAX_POINTS_PER_TILE; for the native default, a stored count) raises
    DecodeLimitError before anything is decoded."""
    if density is not None and n_points is not None:
        raise InvalidPointCloudError("give either a density or a point count, not both")
    if not 1 <= max_tile_points <= MAX_POINTS_PER_TILE:
        raise InvalidPointCloudError(f"the points-per-tile limit must be 1 .. {MAX_POINTS_PER_TILE:,}, "
                                     f"got {max_tile_points}")
    stored = np.array([entry.n_points for entry in entries], dtype=np.int64)
    if density is not None:
        if not (np.isfinite(density) and density > 0):
            raise InvalidPointCloudError(f"density must be a positive number of points per m^3, got {density}")
        sides = [np.maximum(entry.frame_extent_m(np.asarray(header.tile_size)), MIN_DENSITY_EXTENT_M)
                 for entry in entries]
        counts = [int(min(round(density * float(np.prod(side))), 2**62)) for side in sides]
    elif n_points is not None:
        if isinstance(n_points, bool) or not isinstance(n_points, (int, np.integer)) or n_points < 1:
            raise InvalidPointCloudError(f"point count must be an integer of at least 1, got {n_points}")
        share = n_points * stored / max(int(stored.sum()), 1)
        counts = np.floor(share).astype(np.int64)
        counts[np.argsort(-(share - counts), kind="stable")[:n_points - int(counts.sum())]] += 1
        counts = [int(c) for c in counts]
    else:
        counts = [int(c) for c in stored]
    if max(counts, default=0) > max_tile_points:
        raise DecodeLimitError(f"that decodes {max(counts):,} points in one tile, more than the limit of "
                               f"{max_tile_points:,} points per tile; allow more with --max-tile-points N "
                               f"(API: max_tile_points=N, at most {MAX_POINTS_PER_TILE:,})")
    if density is None and n_points is None and header.default_count is DefaultCount.native:
        return [None] * len(entries)
    return counts


def check_model(model, header: Header, name: str) -> None:
    """Refuse a model whose weights differ from the ones the file was compressed with (a version 7 file naming a
    shipped model of other weights than this build's holds only the digest's prefix), unless those are an earlier
    version of the model with the same decoder (`config.decodes_files_of`: only the encoder was retrained)."""
    from mapsqueeze.model.config import decodes_files_of

    if not decodes_files_of(model.weights_sha256, model.config, header.weights_sha256):
        raise ModelError(
            f"{name} was compressed with model {header.model_id!r} (weights sha256 {header.weights_sha256[:16]}...), "
            f"but the given model {model.model_id!r} has weights {model.weights_sha256[:16]}...; "
            "pass the model used for compression (--model NAME|PATH)")


def _embedding_from_payload(header: Header, entry: TileEntry, payload: bytes, label: str
                            ) -> tuple[np.ndarray, np.ndarray]:
    return _network_payload(header, entry, payload, label)[:2]


def _network_payload(header: Header, entry: TileEntry, payload: bytes, label: str
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """(embedding points, features, patch choices or None) of a network tile's payload."""
    stream = None
    if PostFilter.parse(entry.post_filter).per_patch:
        stream, payload = split_patch_choices(payload, label)
    points, features = header.latent.decode(payload, entry.n_points, label)
    if len(points) == 0:
        raise ContainerError(f"{label}: network payload holds no embedding points")
    return points, features, None if stream is None else decode_patch_choices(stream, len(points), label)


def _undecodable(label: str, exc: Exception) -> ContainerError:
    return ContainerError(f"{label}: undecodable payload ({exc})")


def decode_embedding(reader: ContainerReader, position: int) -> tuple[np.ndarray, np.ndarray]:
    """The embedding of network-coded tile `position`: (k, 3) float32 point positions relative to `tile_frame`
    (metres) and their (k, n_features) float32 features."""
    entry = reader.entries[position]
    label = f"{reader.name}: {entry.label(position)}"
    if entry.coding is not TileCoding.network:
        raise ContainerError(f"{label} is coded {entry.coding.name}, it holds no embedding")
    try:
        return _embedding_from_payload(reader.header, entry, reader.payload(position), label)
    except MapsqueezeError:
        raise
    except (ValueError, IndexError, OverflowError) as exc:
        raise _undecodable(label, exc) from None


def decode_payload(header: Header, entry: TileEntry, payload: bytes, model, count: int | None, label: str,
                   max_tile_points: int = DEFAULT_MAX_TILE_POINTS, faces: tuple[InternalFace, ...] = ()
                   ) -> np.ndarray:
    """A tile's payload bytes decoded to `count` float32 points relative to `tile_frame`, all inside the tile's
    bounds (count None: the coding's native count, e.g. the network's whole output inside the box after the
    tile's post-filter). A network tile whose native count (decoded whole, then resampled) is above
    `max_tile_points` is refused whatever `count` is. A network tile's output goes through the post-filter
    its table entry signals (`codec.postfilter`) and the density rule at the `faces` it shares with other tiles
    of the file (`seams.internal_faces`; none: the tile as the encoder sees it) before it is resampled to `count`.

    The network grows surfaces past the tile's bounds box; those points are dropped (the neighbouring tile codes
    that space) and the count is restored from the points inside (`tilepoints.keep_inside`), so tile faces show
    no seams.
    """
    tile_size = np.asarray(header.tile_size)
    try:
        if entry.coding is TileCoding.raw:
            local = resample_to_count(
                decode_raw_tile(payload, tile_size, entry.n_points, label, header.raw_step_m), count)
        elif entry.coding is TileCoding.octree:
            local = octree_points(decode_octree_tile(payload, tile_size, entry.n_points, label),
                                  entry.frame_extent_m(tile_size), count)
        else:
            points, features, choices = _network_payload(header, entry, payload, label)
            native = (len(points) * int(np.prod(model.config.upsampling_factors))
                      * (1 + PostFilter.parse(entry.post_filter).spread_copies))
            if native > max_tile_points:  # decoded whole before any resampling to `count`
                raise DecodeLimitError(f"{label}: its native count of {native:,} points is more than the limit of "
                                       f"{max_tile_points:,} points per tile; allow more with --max-tile-points N "
                                       f"(API: max_tile_points=N, at most {MAX_POINTS_PER_TILE:,})")
            local = network_points(model, points, features, entry.frame_extent_m(tile_size), count,
                                   entry.post_filter, faces, choices)
    except MapsqueezeError:
        raise
    except (ValueError, IndexError, OverflowError) as exc:
        raise _undecodable(label, exc) from None
    return local


def iter_decoded_tiles(
    source: bytes | str | os.PathLike,
    model=None,
    bbox: Sequence[float] | None = None,
    density: float | None = None,
    n_points: int | None = None,
    progress: ProgressCallback | None = None,
    max_tile_points: int = DEFAULT_MAX_TILE_POINTS,
    workers: int | None = 1,
    dask_scheduler: str | None = None,
    device: str = "cpu",
) -> Iterator[np.ndarray]:
    """Decode a .msq buffer or file tile by tile: yields each tile's (k, 3) float64 world points, in file order
    (tiles left empty by the counts or the bbox crop are skipped). Memory: one tile.

    model: a CompressionModel, run where it was loaded, or a name or path (default: the model id stored in the
    file), loaded on `device` (a checked name, `devices.device_name`); its weights must match the file's SHA-256. bbox: six numbers x0,y0,z0,x1,y1,z1 (metres); only tiles whose point box intersects it are
    read and decoded, and the output is cropped to it. density / n_points / max_tile_points: see `target_counts`.
    Payloads are read here and decoded by `workers` threads (None: one per core) or on the Dask cluster at
    `dask_scheduler` (`codec.executor`); the points are the same whatever runs them.
    """
    for cloud in iter_decoded_clouds(source, model, bbox, density, n_points, progress, max_tile_points,
                                     attributes=False, workers=workers, dask_scheduler=dask_scheduler, device=device):
        yield cloud.points


def iter_decoded_clouds(
    source: bytes | str | os.PathLike,
    model=None,
    bbox: Sequence[float] | None = None,
    density: float | None = None,
    n_points: int | None = None,
    progress: ProgressCallback | None = None,
    max_tile_points: int = DEFAULT_MAX_TILE_POINTS,
    attributes: bool = True,
    workers: int | None = 1,
    dask_scheduler: str | None = None,
    device: str = "cpu",
) -> Iterator[PointCloud]:
    """As `iter_decoded_tiles`, yielding each tile as a PointCloud: its world points, the attributes coded in the
    file (each decoded point takes its nearest attribute voxel's values; none with attributes=False) and the
    file's metadata."""
    box = None if bbox is None else parse_bbox(bbox)
    for tile in iter_tile_points(source, model, bbox, density, n_points, progress, max_tile_points, attributes,
                                 workers, dask_scheduler, device):
        world, values = tile.place(tile.take()), tile.values
        if box is not None:
            inside = ((world >= box[0]) & (world <= box[1])).all(axis=1)
            world, values = world[inside], {name: v[inside] for name, v in values.items()}
        if len(world):
            yield PointCloud(world, values, tile.metadata)
        del world, values


class DecodedTile:
    """One decoded tile before it is placed: `frame` (float64 (3,) world origin of its points), its points
    relative to it (`take`), the attribute `values` of those points and the file's `metadata`."""

    def __init__(self, frame: np.ndarray, points: np.ndarray, values: dict, metadata: dict):
        self.frame, self._points, self.values, self.metadata = frame, points, values, metadata

    def take(self) -> np.ndarray:
        """The (k, 3) float32 points, handed over once (the tile keeps no reference, so they are freed as soon
        as the caller is done with them)."""
        points, self._points = self._points, None
        return points

    def place(self, points: np.ndarray) -> np.ndarray:
        """float64 world points `frame` + `points` of (k, 3) float32 rows of this tile, added column by column
        (numpy's (k, 3) + (3,) runs a 3-long inner loop per row, ~4x slower; the same sums)."""
        world = points.astype(np.float64)
        for axis in range(3):
            world[:, axis] += self.frame[axis]
        return world


def iter_tile_points(
    source: bytes | str | os.PathLike,
    model=None,
    bbox: Sequence[float] | None = None,
    density: float | None = None,
    n_points: int | None = None,
    progress: ProgressCallback | None = None,
    max_tile_points: int = DEFAULT_MAX_TILE_POINTS,
    attributes: bool = True,
    workers: int | None = 1,
    dask_scheduler: str | None = None,
    device: str = "cpu",
) -> Iterator[DecodedTile]:
    """As `iter_decoded_clouds` before the tiles are placed in the world and cropped to `bbox` (which selects
    them): a DecodedTile per decoded tile, so that a writer may place a tile part by part
    (`api.decompress_file`)."""
    reader, stream = open_container(source)
    with stream:
        header = reader.header
        box = None if bbox is None else parse_bbox(bbox)
        selected = [position for position, entry in enumerate(reader.entries)
                    if box is None or _intersects(tile_world_bounds(header, entry), box)]
        counts = target_counts(header, [reader.entries[p] for p in selected], density, n_points, max_tile_points)
        if any(reader.entries[p].coding is TileCoding.network for p in selected):
            model = _load_matching_model(model, header, reader.name, device)
        schema = reader.attribute_schema
        metadata = schema.metadata if schema else {}
        jobs = [(position, count) for position, count in zip(selected, counts) if count != 0]
        occupied = {entry.index for entry in reader.entries}
        faces = {position: internal_faces(reader.entries[position], occupied, np.asarray(header.tile_size))
                 for position, _ in jobs}
        payloads = ((reader.entries[position], reader.payload(position), count,
                     f"{reader.name}: {reader.entries[position].label(position)}", faces[position])
                    for position, count in jobs)
        support = attributes and bool(reader.attribute_entries) and reader.version >= ATTRIBUTES_ON_DECODED_GEOMETRY
        context = (header, model, max_tile_points, support)
        executor = open_executor(workers, dask_scheduler, len(jobs))
        try:
            decoded = executor.map(_decode_job, context, payloads)
            for done, (position, count) in enumerate(zip(selected, counts), start=1):
                if count != 0:
                    local, native = next(decoded)
                    values = {}
                    if attributes and reader.attribute_entries:
                        values = _tile_attributes(reader, position, local, native,
                                                  count is None and not faces[position])
                    elif attributes and schema and schema.specs:  # constant attributes only
                        values = with_constants(schema, {}, len(local))
                    tile = DecodedTile(tile_frame(header, reader.entries[position]), local, values, metadata)
                    del local, native, values  # the tile's points are released once its consumer is done
                    yield tile
                    del tile
                if progress:
                    progress(done, len(selected))
        finally:
            executor.close(abort=sys.exc_info()[0] is not None)


def _tile_attributes(reader: ContainerReader, position: int, local: np.ndarray, native: np.ndarray | None,
                     at_native: bool) -> dict[str, np.ndarray]:
    """The attributes of a tile's decoded points `local` from its attribute stream; `native`: the tile's default
    decoded points (the field's support; versions 1-2 code their own voxels), of which `local` is one when
    `at_native`."""
    label = f"{reader.name}: {reader.entries[position].label(position)}"
    stream, schema = reader.attribute_stream(position), reader.attribute_schema
    tile_size = np.asarray(reader.header.tile_size)
    if native is None:
        return decode_legacy_tile_attributes(stream, local, schema, tile_size, label)
    return decode_tile_attributes(stream, native, None if at_native else local, schema, tile_size, label,
                                  crc_optional=reader.version < SUPPORT_CRC_VERSION)


def _decode_job(context: tuple[Header, object, int, bool],
                item: tuple[TileEntry, bytes, int | None, str, tuple[InternalFace, ...]]
                ) -> tuple[np.ndarray, np.ndarray | None]:
    """One tile's job: (table entry, payload bytes, point count, label, faces shared with other tiles) -> float32
    points (`decode_payload`) and, when the context asks for the attribute support, the tile's default decoded
    points as the encoder sees them (at the native count on the CPU, the points before the density rule at the
    faces; else decoded again at the native count, up to MAX_POINTS_PER_TILE); context: the container's header,
    the model, the points-per-tile limit and whether the support is wanted."""
    header, model, max_tile_points, support = context
    entry, payload, count, label, faces = item
    if support and count is None and getattr(model, "device", "cpu") == "cpu":
        native = decode_payload(header, entry, payload, model, None, label, max_tile_points)
        return thin_at_faces(native, faces), native
    local = decode_payload(header, entry, payload, model, count, label, max_tile_points, faces)
    if not support:
        return local, None
    return local, attribute_support(header, entry, payload, model, label)


def attribute_support(header: Header, entry: TileEntry, payload: bytes, model, label: str) -> np.ndarray:
    """The tile's points that carry its attribute field (version >= 3): its default decoded points, decoded on the
    CPU whatever device `model` runs on (other devices round differently in the last bits, which can move a point
    into another voxel), up to MAX_POINTS_PER_TILE."""
    cpu_model = model.on_cpu() if hasattr(model, "on_cpu") else model  # a model only when the tile needs one
    return decode_payload(header, entry, payload, cpu_model, None, label, MAX_POINTS_PER_TILE)


def _intersects(a: np.ndarray, b: np.ndarray) -> bool:
    return bool((a[0] <= b[1]).all() and (b[0] <= a[1]).all())


def _load_matching_model(model, header: Header, name: str, device: str = "cpu"):
    """The given model (object, shipped name or the user's path), or the shipped model the file names: a model id
    read from a file never resolves to a path. A name or path is loaded on `device`. Its weights and grid must match
    the file's."""
    from mapsqueeze.model import load_model, shipped_models

    if model is None:
        if header.model_id not in shipped_models():
            raise ModelError(f"{name} was compressed with model {header.model_id!r}, not a shipped model "
                             f"({', '.join(shipped_models()) or 'none shipped'}); pass it with --model PATH")
        model = load_model(header.model_id, device, shipped_only=True)
    elif isinstance(model, (str, os.PathLike)):
        model = load_model(model, device)
    check_model(model, header, name)
    config = model.config
    if header.n_features != config.embedding_dim:
        raise ContainerError(f"{name}: the header states {header.n_features} embedding channels, model "
                             f"{model.model_id!r} has {config.embedding_dim}")
    if header.subsampling_dist_m != config.subsampling_dist or header.tile_size != tuple(config.tile_size):
        raise ContainerError(f"{name}: the header's grid (r_s {header.subsampling_dist_m:g} m, tiles "
                             f"{header.tile_size} m) differs from model {model.model_id!r}'s "
                             f"(r_s {config.subsampling_dist:g} m, tiles {tuple(config.tile_size)} m)")
    return model
