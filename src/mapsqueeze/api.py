"""Public Python API: compress whole maps to .msq bytes or files and back.

    data = mapsqueeze.compress(points)                   # (N, 3) float64 metres -> bytes (model "e1", precision q)
    cloud = mapsqueeze.decompress(data)                  # -> (K, 3) float64 metres (native count, see docs)
    data = mapsqueeze.compress(points, attributes={"intensity": values})   # + per-point attributes
    cloud = mapsqueeze.decompress_cloud(data)            # -> PointCloud: points, attributes, metadata
    mapsqueeze.compress_file("map.ply", "map.msq")
    mapsqueeze.decompress_file("map.msq", "out.las", bbox=(x0, y0, z0, x1, y1, z1))
    data = mapsqueeze.compress(points, device="cuda")     # the network on a GPU (default "cpu": no torch)
"""

from __future__ import annotations

import contextlib
import dataclasses
import os
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mapsqueeze.codec.attributes import CONSTANT, CONTINUOUS, AttributeSchema
from mapsqueeze.codec.compress import AttributeOptions, ProgressCallback, compress_chunks, compress_map
from mapsqueeze.codec.container import DEFAULT_MAX_TILE_POINTS, TileCoding, open_container
from mapsqueeze.codec.decompress import (
    decode_embedding,
    iter_decoded_clouds,
    iter_decoded_tiles,
    iter_tile_points,
    tile_frame,
    tile_origin,
    tile_world_bounds,
)
from mapsqueeze.codec.modes import RateTarget
from mapsqueeze.codec.embedding import Precision
from mapsqueeze.codec.octreetile import octree_leaf_m
from mapsqueeze.errors import InvalidPointCloudError, MapsqueezeError
from mapsqueeze.io.atomic import remove_dead_work_dirs
from mapsqueeze.io.ply import write_ply_stream
from mapsqueeze.io.pointcloud import FLOAT32_SAFE_ABS_M
from mapsqueeze.io import (
    PointCloud,
    atomic_write_bytes,
    check_output_path,
    drop_zero_points,
    format_name,
    iter_point_clouds,
    validate_attributes,
    validate_points,
    warn_of_crs_loss,
    work_dir,
    write_point_chunks,
)

DEFAULT_MODEL = "e1"
DEFAULT_PRECISION = "q"

SPILL_PREFIX = "mapsqueeze-decoded-"
"""Name prefix of decompress_file's spill folders (`io.work_dir`)."""

PLACE_CHUNK_POINTS = 1 << 16
"""Points of a decoded tile placed in the world (float64) and written at once by decompress_file's binary PLY."""

SPILL_CHUNK_POINTS = 1 << 17
"""Points per chunk that decompress_file reads back from its spill files and writes (3 MB of coordinates; the
writer's checks make a few temporaries of that size)."""

COMPRESS_CHUNK_POINTS = 1 << 16
"""Points per chunk that compress_file reads (1.5 MB of coordinates): its second pass tiles and spills a chunk while
the first tiles are encoded (`compress_chunks`), so the chunk's temporaries add to the encoders' memory."""


RATE_TARGET_MODELS = ("e0", "e1", "e2", "e3")
"""The models a rate target (max_error / bpp) chooses from when no model is given."""


def _device(device: str, model, dask_scheduler: str | None) -> str:
    """The checked name of the device the network runs on (`model.devices.device_name`; "cpu" imports no torch).
    MapsqueezeError for a device this machine lacks, for a device other than the CPU with a Dask cluster, and for
    one other than a given CompressionModel's own."""
    if str(device) == "cpu":
        return "cpu"
    from mapsqueeze.model.devices import device_name, same_device

    name = device_name(device)
    if name == "cpu":
        return name
    if dask_scheduler is not None:
        raise MapsqueezeError(f"device {name!r} with a Dask cluster: the network would run on the cluster's workers, "
                              "which may have no GPU; give a device or a cluster (--dask-scheduler), not both")
    if model is not None and not isinstance(model, (str, os.PathLike)):
        own = device_name(getattr(model, "device", "cpu"))
        if not same_device(own, name):
            raise MapsqueezeError(f"the given model {getattr(model, 'model_id', '')!r} runs on {own!r}, not on device "
                                  f"{name!r}: give its name or directory, or load it there "
                                  f"(load_model(name, device={name!r}))")
    return name


def _model(model, device: str = "cpu"):
    """A CompressionModel as is, or load one by shipped name or directory on `device` (a `_device` name)."""
    if isinstance(model, (str, os.PathLike)):
        from mapsqueeze.model import load_model

        return load_model(model, device)
    return model


def _target(max_error: float | None, bpp: float | None, fallback: bool, post_filter: str) -> RateTarget:
    """The RateTarget of compress's arguments."""
    return RateTarget(max_error, bpp, fallback, post_filter)


def _models(model, target: RateTarget, device: str):
    """The model to compress with, or under a rate target without a model, the list of shipped ones to pick from,
    loaded on `device` (a `_device` name) where given by name."""
    if model is None:
        return ([_model(name, device) for name in RATE_TARGET_MODELS] if target.given
                else _model(DEFAULT_MODEL, device))
    return _model(model, device)


def compress(points: np.ndarray, model=None, precision: str | Precision = DEFAULT_PRECISION, *,
             refine_steps: int = 0, max_error: float | None = None, bpp: float | None = None,
             fallback: bool = True, post_filter: str = "patch", progress: ProgressCallback | None = None,
             keep_zero_points: bool = False, attributes: dict[str, np.ndarray] | None = None, metadata: dict | None = None,
             attribute_options: AttributeOptions = AttributeOptions(),
             workers: int | None = None, dask_scheduler: str | None = None, device: str = "cpu") -> bytes:
    """(N, 3) float64 map points (metres, e.g. UTM) -> .msq bytes.

    model: shipped name (e0..e3), model directory or loaded CompressionModel (default e1; with max_error or bpp
    and no model, the one of e0..e3 that meets the target best). Each tile is stored with the coding its mode
    decision picks (`codec.modes`): by default the lowest D_e at no more bytes than the network's payload;
    max_error (metres): the smallest coding with D_e <= max_error; bpp: the lowest D_e within that many bits per
    point (the smallest file when nothing fits). fallback=False offers tiles only the network (and raw coding when sparse), not the octree (the paper's
    mode, with post_filter="off"). post_filter: the decode post-filter per network tile (`codec.postfilter`, one byte per tile):
    "patch" (default: patch planes where they raise the tile's IoU, ~10 ms per tile; without max_error or bpp,
    their options chosen per decoder patch where that pays, +0.4-0.8 s per tile), "auto" (neighbour planes:
    IoU +0.01-0.04 on the real submaps, D_e up to 5 % higher, seconds per tile to encode and decode) or "off" (the
    paper's decode). precision: f32, f16 or q.
    refine_steps: encode-time refinement of each tile's embedding (0: the paper's encoder; 20: ~10 % lower D_e at
    the same size, each step ~0.35 CPU-s per dense 40 m tile on the CPU, whose unrefined encoding takes ~0.25;
    decoding unchanged).
    progress(done, total) is called after each tile.
    Points at exactly (0, 0, 0), which sensors write for "no return", are left out (with their attributes) unless
    keep_zero_points. attributes: name -> (N,) values, coded per tile as chosen by attribute_options (which, voxel
    edge, step); metadata: JSON-serialisable file metadata (e.g. `PointCloud.metadata` of a LAS file) stored in the
    file. workers: threads encoding tiles in parallel (None: one per core); dask_scheduler: run the tiles on a
    Dask cluster at this address instead ("local": a LocalCluster of `workers` processes). The bytes are the same.
    device: where the models given by name (or the default ones) run the network, its encoder, the refinement
    steps and the decoder the mode decision measures: "cpu" (numpy without torch: the same bytes on any machine),
    "cuda" or "cuda:N" (torch on that GPU, refinement through its autograd: the same rate points within float32
    rounding, not the same bytes). A loaded CompressionModel runs where it was loaded; a device other than "cpu"
    must be its own. MapsqueezeError before any work for a device this machine lacks, and for one other than
    "cpu" with dask_scheduler (a cluster's workers may have no GPU).
    """
    device = _device(device, model, dask_scheduler)
    precision = precision if isinstance(precision, Precision) else Precision.parse(precision)
    if not keep_zero_points:
        points = validate_points(points, name="map")
        attributes = validate_attributes(attributes, len(points), name="map")
        kept, n_zero = drop_zero_points(points, name="map")
        if n_zero:
            nonzero = points.any(axis=1)
            points, attributes = kept, {name: values[nonzero] for name, values in attributes.items()}
    target = _target(max_error, bpp, fallback, post_filter)
    return compress_map(points, _models(model, target, device), precision, progress=progress, refine_steps=refine_steps,
                        attributes=attributes, metadata=metadata, attribute_options=attribute_options,
                        workers=workers, dask_scheduler=dask_scheduler, target=target)


def decompress(data: bytes | str | os.PathLike, *, model=None, bbox: Sequence[float] | None = None,
               density: float | None = None, n_points: int | None = None,
               progress: ProgressCallback | None = None,
               max_tile_points: int = DEFAULT_MAX_TILE_POINTS, workers: int | None = None,
               dask_scheduler: str | None = None, device: str = "cpu") -> np.ndarray:
    """.msq bytes (or a .msq file path) -> (K, 3) float64 world points.

    By default every tile decodes to the count its file states: the native count of its coding (the network's
    whole output inside the tile, thinned where it piles up at a face shared with another tile, `codec.seams`;
    docs/model.md, "Decoded density"), or for version 1 files its input count. bbox=(x0, y0, z0, x1, y1, z1) decodes only the
    tiles that intersect it and crops to it; density (points per m^3 of each tile's box) or n_points (in total,
    split over the tiles decoded by their input counts; with a bbox, counted before the crop) choose another
    density. model defaults to the shipped model named in the file; its weights must match the
    file's. A tile asked for more than max_tile_points points raises DecodeLimitError (a crafted file may claim
    millions of points in a few bytes). workers: threads decoding tiles in parallel (None: one per core; 1: this
    thread); dask_scheduler, device: as in `compress` (the decoder runs there; a file decodes on any device, the
    points within float32 rounding of the CPU's).
    """
    device = _device(device, model, dask_scheduler)
    tiles = list(iter_decoded_tiles(data, model, bbox, density, n_points, progress, max_tile_points,
                                    workers=workers, dask_scheduler=dask_scheduler, device=device))
    return np.concatenate(tiles) if tiles else np.zeros((0, 3), dtype=np.float64)


def decompress_cloud(data: bytes | str | os.PathLike, *, model=None, bbox: Sequence[float] | None = None,
                     density: float | None = None, n_points: int | None = None,
                     progress: ProgressCallback | None = None,
                     max_tile_points: int = DEFAULT_MAX_TILE_POINTS, workers: int | None = None,
                     dask_scheduler: str | None = None, device: str = "cpu") -> PointCloud:
    """As `decompress`, with every attribute coded in the file (dtypes restored) and the file's metadata."""
    device = _device(device, model, dask_scheduler)
    tiles = list(iter_decoded_clouds(data, model, bbox, density, n_points, progress, max_tile_points,
                                     workers=workers, dask_scheduler=dask_scheduler, device=device))
    if not tiles:
        return PointCloud(np.zeros((0, 3), dtype=np.float64))
    return PointCloud(np.concatenate([tile.points for tile in tiles]),
                      {name: np.concatenate([tile.attributes[name] for tile in tiles]) for name in tiles[0].attributes},
                      tiles[0].metadata)


@dataclass(frozen=True)
class ContainerInfo:
    """Summary of a .msq file (`mapsqueeze info`)."""

    file_bytes: int
    header_bytes: int  # header, tile table and CRCs
    model_id: str
    weights_sha256: str
    precision: str
    subsampling_dist_m: float
    tile_size: tuple[float, float, float]
    origin: tuple[float, float, float]
    n_points: int
    n_tiles: int
    n_raw_tiles: int
    bounds: np.ndarray  # (2, 3) world box of all tiles' points (metres)
    zero_points_dropped: int = 0  # input points at exactly (0, 0, 0) left out (compress_file only)
    nan_points_dropped: int = 0  # input points with a NaN coordinate left out (a PCD's "no return"; compress_file)
    attribute_schema: AttributeSchema | None = None  # coded attributes and file metadata (None: geometry only)
    attribute_bytes: int = 0  # bytes of the attribute section (schema, metadata, streams)

    @property
    def attributes(self) -> tuple[str, ...]:
        return tuple(spec.name for spec in self.attribute_schema.specs) if self.attribute_schema else ()

    @property
    def metadata(self) -> dict:
        return self.attribute_schema.metadata if self.attribute_schema else {}

    def attribute_summary(self) -> str:
        """One line: each attribute with its coding, the voxel edge and the bits per point they take."""
        schema = self.attribute_schema
        if not schema or not schema.specs:
            return "none"
        parts = [f"{spec.name} ({spec.dtype.name}, " + (f"median, step {spec.step:.6g})" if spec.kind == CONTINUOUS
                                                        else f"constant {spec.constant(1)[0]})" if spec.kind == CONSTANT
                                                        else "majority)") for spec in schema.specs]
        return (", ".join(parts) + f"; voxel {schema.voxel_m:g} m; {self.attribute_bytes:,} bytes, "
                f"{8.0 * self.attribute_bytes / self.n_points:.4f} bits per point")
    tile_modes: dict[str, int] = dataclasses.field(default_factory=dict)  # tiles per coding: "network", "raw", ...
    default_count: str = "input"  # what a plain decompress gives per tile: "input" (its input count) or "native"

    @property
    def bits_per_point(self) -> float:
        return 8.0 * self.file_bytes / self.n_points


def info(source: bytes | str | os.PathLike) -> ContainerInfo:
    """Read the header and tile table of a .msq buffer or file (of the payloads, only octree tiles' are read,
    for their leaf edge)."""
    reader, stream = open_container(source)
    with stream:
        header = reader.header
        boxes = np.array([tile_world_bounds(header, entry) for entry in reader.entries])
        return ContainerInfo(
            file_bytes=reader.file_size,
            header_bytes=reader.header_bytes(),
            model_id=header.model_id,
            weights_sha256=header.weights_sha256,
            precision=header.precision.name,
            subsampling_dist_m=header.subsampling_dist_m,
            tile_size=header.tile_size,
            origin=header.origin,
            n_points=header.n_points,
            n_tiles=header.n_tiles,
            n_raw_tiles=sum(entry.coding is TileCoding.raw for entry in reader.entries),
            bounds=np.stack([boxes[:, 0].min(axis=0), boxes[:, 1].max(axis=0)]),
            attribute_schema=reader.attribute_schema,
            attribute_bytes=reader.file_size - (reader.entries[-1].offset + reader.entries[-1].length),
            tile_modes=_tile_modes(reader),
            default_count=header.default_count.name,
        )


def _tile_modes(reader) -> dict[str, int]:
    """Tiles per coding: octree tiles by leaf edge (read from the first bytes of their payloads), network tiles by
    decode post-filter setting."""
    from mapsqueeze.codec.postfilter import OFF, PostFilter

    modes: dict[str, int] = {}
    for position, entry in enumerate(reader.entries):
        mode = entry.coding.name
        if entry.coding is TileCoding.octree:
            mode += f" {octree_leaf_m(reader.payload(position), entry.label(position)):g} m"
        elif entry.coding is TileCoding.network and entry.post_filter != OFF:
            mode += f" ({PostFilter.parse(entry.post_filter).describe()})"
        modes[mode] = modes.get(mode, 0) + 1
    return dict(sorted(modes.items()))


@dataclass(frozen=True)
class TileInfo:
    """One tile of a .msq file (`tiles`): where it lies, how it is coded and what it stores."""

    index: tuple[int, int, int]  # grid cell: lower corner at origin + index * tile_size
    coding: str  # how its points are stored: "network" (an embedding decoded by the model), "raw" or "octree"
    model_id: str | None  # the model that decodes it (None: no network needed)
    n_points: int  # points of the input map in the tile (the default decoded count of version 1 files only)
    payload_bytes: int
    cell: np.ndarray  # (2, 3) float64 world box of the grid cell (metres)
    bounds: np.ndarray  # (2, 3) float64 world box of the tile's input points (metres)
    embedding: np.ndarray  # (k, 3) float64 world positions of the embedding points (metres); (0, 3) if none


def tiles(source: bytes | str | os.PathLike) -> list[TileInfo]:
    """Every tile of a .msq buffer or file in file order, with its embedding points (no network runs)."""
    reader, stream = open_container(source)
    with stream:
        header = reader.header
        result = []
        for position, entry in enumerate(reader.entries):
            network = entry.coding is TileCoding.network
            embedding = (tile_frame(header, entry) + decode_embedding(reader, position)[0] if network
                         else np.zeros((0, 3)))
            lower = tile_origin(header, entry)
            result.append(TileInfo(
                index=entry.index, coding=entry.coding.name, model_id=header.model_id if network else None,
                n_points=entry.n_points, payload_bytes=entry.length,
                cell=np.stack([lower, lower + np.asarray(header.tile_size)]),
                bounds=tile_world_bounds(header, entry), embedding=np.asarray(embedding, dtype=np.float64)))
        return result


def compress_file(input_path: str | os.PathLike, output_path: str | os.PathLike, model=None,
                  precision: str | Precision = DEFAULT_PRECISION, *, refine_steps: int = 0,
                  max_error: float | None = None, bpp: float | None = None, fallback: bool = True,
                  post_filter: str = "patch", progress: ProgressCallback | None = None,
                  keep_zero_points: bool = False,
                  format: str | None = None,
                  attribute_options: AttributeOptions = AttributeOptions(), workers: int | None = None,
                  dask_scheduler: str | None = None, device: str = "cpu") -> ContainerInfo:
    """Read a point-cloud file in chunks, compress it, write the .msq atomically; returns the written file's summary
    (with `zero_points_dropped`, the points at exactly (0, 0, 0) left out unless keep_zero_points, and
    `nan_points_dropped`, a PCD's points with a NaN coordinate, which the reader leaves out).

    format: the input's format (one of `mapsqueeze.io.SUPPORTED_FORMATS`; default from the extension). The output
    path is checked before any work. Memory is bounded by a chunk of the input and one tile (see `compress_chunks`),
    not by the map's size; the bytes are those `compress` gives for the file's points, attributes and metadata
    (`read_point_cloud`), coded as attribute_options says; workers / dask_scheduler / device as in `compress` (one
    tile in memory per worker).
    """
    device = _device(device, model, dask_scheduler)
    precision = precision if isinstance(precision, Precision) else Precision.parse(precision)
    format_name(input_path, format)
    check_output_path(output_path, inputs=(input_path,))
    target = _target(max_error, bpp, fallback, post_filter)
    model = _models(model, target, device)
    dropped = [0, 0]  # points at (0, 0, 0), points with a NaN coordinate

    def chunks():
        dropped[:] = [0, 0]
        kept = 0
        for chunk in iter_point_clouds(input_path, format, COMPRESS_CHUNK_POINTS):
            dropped[1] += chunk.nan_points_dropped
            if not keep_zero_points:
                points, n_zero = drop_zero_points(chunk.points, allow_empty=True)
                if n_zero:
                    nonzero = chunk.points.any(axis=1)
                    chunk = PointCloud(points, {name: values[nonzero] for name, values in chunk.attributes.items()},
                                       chunk.metadata)
                dropped[0] += n_zero
            kept += len(chunk)
            if len(chunk):
                yield chunk
        if dropped[0] and not kept:
            zero, nan = dropped
            if nan:  # a PCD's NaN points are left out by the reader: count them with the zero ones
                raise InvalidPointCloudError(
                    f"{input_path}: no points: {nan:,} of {zero + nan:,} points {'has' if nan == 1 else 'have'} NaN "
                    f"coordinates (PCD 'no return' values) and the other {zero:,} {'lies' if zero == 1 else 'lie'} at "
                    "(0, 0, 0) (sensor 'no return' values); keep those with --keep-zero-points")
            raise InvalidPointCloudError(f"{input_path}: all {zero:,} points lie at (0, 0, 0) (sensor "
                                         "'no return' values); keep them with --keep-zero-points")

    data = compress_chunks(chunks, model, precision, progress=progress, refine_steps=refine_steps,
                           attribute_options=attribute_options, workers=workers, dask_scheduler=dask_scheduler,
                           target=target)
    atomic_write_bytes(output_path, data)
    return dataclasses.replace(info(data), zero_points_dropped=dropped[0], nan_points_dropped=dropped[1])


def decompress_file(input_path: str | os.PathLike, output_path: str | os.PathLike, *, model=None,
                    bbox: Sequence[float] | None = None, density: float | None = None, n_points: int | None = None,
                    progress: ProgressCallback | None = None, spill_dir: str | os.PathLike | None = None,
                    max_tile_points: int = DEFAULT_MAX_TILE_POINTS, format: str | None = None,
                    workers: int | None = None, dask_scheduler: str | None = None, attributes: bool = True,
                    device: str = "cpu") -> int:
    """Decode a .msq file (seeking to the tiles needed) and write the points, their attributes and the file's
    metadata atomically; returns the count.

    format: the output's format (one of `mapsqueeze.io.SUPPORTED_FORMATS`; default from the extension).
    attributes=False writes the geometry only (and the metadata), without decoding the attribute streams.

    Tiles are decoded one at a time. A binary PLY without attributes is written as they arrive
    (`io.ply.write_ply_stream`); other outputs go through spill files (in spill_dir, default the system's temporary
    directory; 24 bytes a point plus the attributes), which are then written out chunk by chunk: memory stays
    bounded by a tile and a chunk for the binary formats (see `mapsqueeze.io.write_point_chunks`); workers /
    dask_scheduler / device as in `compress` (one tile in memory per worker).
    """
    device = _device(device, model, dask_scheduler)
    output_format = format_name(output_path, format)  # an unknown format or an unwritable path fails before decoding
    check_output_path(output_path, inputs=(input_path,))
    summary = info(input_path)
    schema = summary.attribute_schema
    specs = schema.specs if schema and attributes else ()
    if output_format == "ply" and not specs:  # streamed: no spill file
        remove_dead_work_dirs(SPILL_PREFIX, spill_dir)
        sizes = []  # points of each tile written

        def tiles() -> Iterator[np.ndarray]:
            options = dict(attributes=False, workers=workers, dask_scheduler=dask_scheduler, device=device)
            if bbox is None:  # each tile placed in the world part by part
                for tile in iter_tile_points(input_path, model, None, density, n_points, progress, max_tile_points,
                                             **options):
                    local = tile.take()
                    sizes.append(len(local))
                    for start in range(0, len(local), PLACE_CHUNK_POINTS):
                        yield tile.place(local[start:start + PLACE_CHUNK_POINTS])
                    del tile, local  # released before the next tile arrives
            else:
                for cloud in iter_decoded_clouds(input_path, model, bbox, density, n_points, progress,
                                                 max_tile_points, **options):
                    sizes.append(len(cloud))
                    yield cloud.points
                    del cloud
            if not sizes:
                raise _nothing_to_write(input_path, bbox, density)

        float32_certain = float(np.abs(summary.bounds).max()) + 1.0 < FLOAT32_SAFE_ABS_M
        count = write_ply_stream(Path(output_path), tiles(), float32_certain, lambda _: sizes[0] * summary.n_tiles)
        warn_of_crs_loss(summary.metadata, output_path, format)
        return count
    with work_dir(SPILL_PREFIX, spill_dir) as spill:
        spill_path = os.path.join(spill, "points.f64")
        streams = [open(os.path.join(spill, f"attribute{column}"), "wb") for column in range(len(specs))]
        try:
            with open(spill_path, "wb") as stream:
                for tile in iter_decoded_clouds(input_path, model, bbox, density, n_points, progress,
                                                max_tile_points, attributes=attributes, workers=workers,
                                                dask_scheduler=dask_scheduler, device=device):
                    stream.write(np.ascontiguousarray(tile.points, dtype="<f8").data)
                    for spec, column in zip(specs, streams):
                        column.write(np.ascontiguousarray(tile.attributes[spec.name], dtype=spec.dtype).data)
        finally:
            for column in streams:
                column.close()
        if os.path.getsize(spill_path) == 0:
            raise _nothing_to_write(input_path, bbox, density)
        n_points = os.path.getsize(spill_path) // 24
        attribute_paths = {spec.name: (os.path.join(spill, f"attribute{column}"), spec.dtype)
                           for column, spec in enumerate(specs)}
        metadata = schema.metadata if schema else {}
        return write_point_chunks(output_path, lambda: _spill_chunks(spill_path, attribute_paths, n_points, metadata),
                                  format)


def _nothing_to_write(input_path, bbox, density: float | None) -> InvalidPointCloudError:
    """The error of a decode with no point: the bbox holds none (at the density, when one is given), or (without a
    bbox) the density gives every tile none."""
    if density is None:
        return InvalidPointCloudError(f"{input_path}: no points to write (the bbox holds no decoded points)")
    if bbox is None:
        return InvalidPointCloudError(f"{input_path}: no points to write (a density of {density:g} points per m^3 "
                                      "decodes every tile to no point)")
    return InvalidPointCloudError(f"{input_path}: no points to write (the bbox holds no decoded points at a density "
                                  f"of {density:g} points per m^3)")


def _spill_chunks(points_path: str, attribute_paths: dict[str, tuple[str, np.dtype]], n_points: int,
                  metadata: dict) -> Iterator[PointCloud]:
    """decompress_file's spill files (float64 points, one file per attribute) read back in clouds of
    SPILL_CHUNK_POINTS points, by plain reads: a memory map would keep every page it had read resident."""
    with contextlib.ExitStack() as files:
        points_file = files.enter_context(open(points_path, "rb"))
        columns = {name: (files.enter_context(open(path, "rb")), dtype)
                   for name, (path, dtype) in attribute_paths.items()}
        for start in range(0, n_points, SPILL_CHUNK_POINTS):
            count = min(SPILL_CHUNK_POINTS, n_points - start)
            yield PointCloud(np.fromfile(points_file, dtype="<f8", count=3 * count).reshape(count, 3),
                             {name: np.fromfile(stream, dtype=dtype, count=count)
                              for name, (stream, dtype) in columns.items()}, metadata)
