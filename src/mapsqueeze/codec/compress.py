"""Whole map -> .msq bytes: tile the map, store each occupied tile with the coding its mode decision picks (the
network's embedding, raw points or an octree; `codec.modes`), pack."""

from __future__ import annotations

import os
import sys
from collections.abc import Callable, Iterable
from dataclasses import dataclass

import numpy as np

from mapsqueeze.codec.attributes import (
    DEFAULT_RELATIVE_STEP,
    DEFAULT_VOXEL_M,
    AttributeSchema,
    build_schema,
    parse_selection,
)
from mapsqueeze.codec.distortion import CandidateDistortion
from mapsqueeze.codec.container import (
    BOUNDS_STEPS,
    MAX_POINTS_PER_TILE,
    AttributeSection,
    DefaultCount,
    Header,
    TileCoding,
    TileRecord,
    frame_origin,
    quantise_bounds,
    serialise_container,
)
from mapsqueeze.codec.embedding import DEFAULT_FEATURE_STEP_STD, Precision
from mapsqueeze.codec.executor import ProgressCallback, open_executor, start_pool_server
from mapsqueeze.codec.latent import LATENT_CODECS, LatentCodec, LatentLayout
from mapsqueeze.codec.modes import Candidate, RateTarget, choose, choose_for_error, choose_for_rate, summary
from mapsqueeze.codec.octreetile import OCTREE_LEAVES_M, encode_octree_tiles, own_leaf_distances
from mapsqueeze.codec.rawtile import RAW_STEP_M, decode_raw_tile, encode_raw_tile
from mapsqueeze.codec.patchchoice import PatchChooser
from mapsqueeze.codec.postfilter import OFF, choose_patch_filter, choose_post_filter
from mapsqueeze.codec.tileattributes import AttributeCoder
from mapsqueeze.codec.tilepoints import keep_inside, network_points, octree_points
from mapsqueeze.errors import InvalidPointCloudError, MapsqueezeError
from mapsqueeze.geometry.bounds import bounding_box
from mapsqueeze.geometry.tiling import fit_grid, tile_map, to_local
from mapsqueeze.geometry.validation import validate_points
from mapsqueeze.io import PointCloud, validate_attributes, work_dir

WORKER_MODULES = ("mapsqueeze.codec.compress", "mapsqueeze.model.compression", "mapsqueeze.geometry.grid",
                  "mapsqueeze.baselines.octree", "mapsqueeze.geometry.cells", "mapsqueeze.codec.compressworker")
"""What compressing workers import (`codec.executor.ProcessExecutor`'s preload): the numpy network, the octree
coder, numba and its kernels, with numba's compiler started (`compressworker`)."""

RAW_POINTS_PER_EMBEDDING = 4
"""A tile with at most this many points per embedding point is coded raw: the decoder, trained to grow each
embedding point into hundreds of points of a dense surface, fits such sparse tiles poorly."""

RAW_CANDIDATE_POINTS_PER_EMBEDDING = 20
"""Raw coding is also tried (and kept when smaller) for tiles with up to this many points per embedding point;
beyond it raw coding (>= 13 bits a point) cannot beat even f32 embeddings (192 bits per embedding point)."""

MAX_REFINE_STEPS = 10_000
"""Encode-time refinement steps accepted at most per tile (`CompressionModel.refine`; a guard against typos)."""

@dataclass(frozen=True)
class AttributeOptions:
    """Which attributes to code and how finely (see codec.attributes).

    selection: "all", "none", or attribute names (a comma-separated string or a sequence). voxel_m: edge of the
    attribute voxels (metres). relative_step: quantisation step of continuous attributes, as a fraction of each
    attribute's range over the map.
    """

    selection: str | tuple[str, ...] = "all"
    voxel_m: float = DEFAULT_VOXEL_M
    relative_step: float = DEFAULT_RELATIVE_STEP


def _attribute_schema(ranges: dict[str, tuple[np.dtype, float, float]], metadata: dict | None,
                      options: AttributeOptions) -> AttributeSchema | None:
    """The schema of the selected attributes, or None when there is nothing to code (a geometry-only file)."""
    names = parse_selection(options.selection, list(ranges))
    if not names and not metadata:
        return None
    return build_schema({name: ranges[name] for name in names}, options.voxel_m, options.relative_step,
                        metadata or {})


def _ranges(attributes: dict[str, np.ndarray]) -> dict[str, tuple[np.dtype, float, float]]:
    return {name: (values.dtype, float(values.min()), float(values.max())) for name, values in attributes.items()}


@dataclass
class _EncodedTile:
    """One tile while the map is being compressed: its table fields, embedding and candidate codings."""

    index: tuple[int, int, int]
    n_points: int
    bounds_lo: tuple[int, int, int]
    bounds_hi: tuple[int, int, int]
    extent_m: np.ndarray  # size of the tile's bounds box (metres)
    points: np.ndarray | None  # network embedding (None when the network is no candidate: too sparse)
    features: np.ndarray | None
    candidates: list[Candidate]  # classical ones at first; the network's is added once coded
    network_d_e: float | None = None  # metres: D_e of the network's output for the (unquantised) embedding
    post_filter: int = OFF  # the network output's decode post-filter (`codec.postfilter`)
    choice: Candidate | None = None

    def record(self) -> TileRecord:
        network = self.choice.coding is TileCoding.network
        return TileRecord(self.index, self.n_points, self.bounds_lo, self.bounds_hi, self.choice.coding,
                          self.choice.payload, self.post_filter if network else OFF)


def compress_map(
    points: np.ndarray,
    model,
    precision: Precision = Precision.q,
    position_step_m: float | None = None,
    feature_step_std: float = DEFAULT_FEATURE_STEP_STD,
    progress: ProgressCallback | None = None,
    refine_steps: int = 0,
    attributes: dict[str, np.ndarray] | None = None,
    metadata: dict | None = None,
    attribute_options: AttributeOptions = AttributeOptions(),
    target: RateTarget = RateTarget(),
    workers: int | None = 1,
    dask_scheduler: str | None = None,
) -> bytes:
    """Compress an (N, 3) float64 map (metres, any coordinate frame) with a loaded CompressionModel, or with the
    one of a list of them whose tile choices meet `target` best (`codec.modes`; every tile is stored with the
    candidate coding the target prefers: the network's embedding, raw points or an octree).

    position_step_m / feature_step_std set the q quantiser (defaults DEFAULT_POSITION_STEP_RS x r_s, at most
    DEFAULT_POSITION_STEP_MAX_M, and
    DEFAULT_FEATURE_STEP_STD). refine_steps > 0 refines each network tile's embedding at encode time
    (`CompressionModel.refine`: slower encoding, lower D_e, same format). Tiles are encoded by `workers` processes
    (None: one per core) or on the Dask cluster at `dask_scheduler` ("local" starts one; `codec.executor`); only
    their compact embeddings and payloads are kept until the file is assembled (q fits its histograms over all tiles
    before coding them). Deterministic: the same points, model and settings give the same bytes, whatever runs them.
    attributes (name -> (N,) values) selected by attribute_options are coded per tile after the geometry, and
    metadata (JSON-serialisable, e.g. the LAS header's) is stored; with neither the file is geometry-only.
    """
    check_refine_steps(refine_steps)
    models, tile_size = _model_list(model)
    points = validate_points(points, name="map")
    attributes = validate_attributes(attributes, len(points), name="map")
    schema = _attribute_schema(_ranges(attributes), metadata, attribute_options)
    origin, shape = fit_grid(*bounding_box(points), tile_size)
    start_pool_server(workers, dask_scheduler, int(np.prod(shape)), WORKER_MODULES)  # it imports while we tile
    tiles = tile_map(points, tile_size, origin=origin, shape=shape)
    coded = [spec.name for spec in schema.specs] if schema else []

    def tile_points():
        return ((tile.index, points[tile.point_indices], {name: attributes[name][tile.point_indices] for name in coded})
                for tile in tiles)

    return _compress_tiles(tile_points, len(tiles), len(points), origin, models, precision, position_step_m,
                           feature_step_std, progress, refine_steps, target, schema, workers, dask_scheduler)


def compress_chunks(
    chunks: Callable[[], Iterable[np.ndarray]],
    model,
    precision: Precision = Precision.q,
    position_step_m: float | None = None,
    feature_step_std: float = DEFAULT_FEATURE_STEP_STD,
    progress: ProgressCallback | None = None,
    spill_dir: str | os.PathLike | None = None,
    refine_steps: int = 0,
    attribute_options: AttributeOptions = AttributeOptions(),
    target: RateTarget = RateTarget(),
    workers: int | None = 1,
    dask_scheduler: str | None = None,
) -> bytes:
    """compress_map for a map read in chunks (e.g. `mapsqueeze.io.iter_points`): memory bounded by one chunk and
    one tile, whatever the map's size. Gives the same bytes as compress_map on the concatenated chunks.

    chunks() is called twice (pass 1: extent, count, attribute ranges; pass 2: points); each call must yield the
    same chunks ((n, 3) float64 arrays, or PointClouds whose attributes and the first one's metadata are coded as
    compress_map's) in the same order. Pass 2 appends every tile's points (and attributes) to spill files in a
    temporary directory (in spill_dir, default the system's; 24 bytes a point plus the attributes), then encodes the
    tiles back one by one and hands them to the encoding workers (memory: one tile per worker).
    """
    check_refine_steps(refine_steps)
    models, tile_size = _model_list(model)
    lowest, highest, n_points = np.full(3, np.inf), np.full(3, -np.inf), 0
    ranges: dict[str, tuple[np.dtype, float, float]] = {}
    metadata = None
    for chunk in map(_as_cloud, chunks()):
        chunk_low, chunk_high = bounding_box(chunk.points)
        lowest, highest = np.minimum(lowest, chunk_low), np.maximum(highest, chunk_high)
        metadata = chunk.metadata if metadata is None else metadata
        for name, (dtype, low, high) in _ranges(chunk.attributes).items():
            previous = ranges.get(name, (dtype, low, high))
            ranges[name] = (dtype, min(low, previous[1]), max(high, previous[2]))
        n_points += len(chunk)
    if n_points == 0:
        raise InvalidPointCloudError("map: the point cloud is empty")
    schema = _attribute_schema(ranges, metadata, attribute_options)
    coded = [(spec.name, spec.dtype) for spec in schema.specs] if schema else []
    origin, shape = fit_grid(lowest, highest, tile_size)  # the grid compress_map fits to the whole map
    # the server imports during pass 2 (the grid's cell count bounds the occupied tiles')
    start_pool_server(workers, dask_scheduler, int(np.prod(shape)), WORKER_MODULES)
    with work_dir("mapsqueeze-tiles-", spill_dir) as spill:
        counts: dict[tuple[int, int, int], int] = {}
        for chunk in map(_as_cloud, chunks()):
            for tile in tile_map(chunk.points, tile_size, origin=origin, shape=shape):
                with open(os.path.join(spill, _spill_name(tile.index)), "ab") as stream:
                    stream.write(chunk.points[tile.point_indices].tobytes())
                for column, (name, dtype) in enumerate(coded):
                    with open(os.path.join(spill, _spill_name(tile.index, column)), "ab") as stream:
                        stream.write(np.asarray(chunk.attributes[name], dtype=dtype)[tile.point_indices].tobytes())
                counts[tile.index] = counts.get(tile.index, 0) + len(tile.point_indices)
        if sum(counts.values()) != n_points:
            raise InvalidPointCloudError("map: the input changed between the two reading passes")
        indices = sorted(counts)  # the order of tile_map: by (i, j, k)
        for index in indices:  # refused before a tile that large is read back into memory
            _check_tile_size(index, counts[index])

        def tile_points():
            return ((index, np.fromfile(os.path.join(spill, _spill_name(index)), dtype=np.float64).reshape(-1, 3),
                     {name: np.fromfile(os.path.join(spill, _spill_name(index, column)), dtype=dtype)
                      for column, (name, dtype) in enumerate(coded)})
                    for index in indices)

        return _compress_tiles(tile_points, len(indices), n_points, origin, models, precision, position_step_m,
                               feature_step_std, progress, refine_steps, target, schema, workers, dask_scheduler)


def _as_cloud(chunk) -> PointCloud:
    """A chunk as a PointCloud with validated points and attributes (bare (n, 3) arrays have none)."""
    if not isinstance(chunk, PointCloud):
        return PointCloud(validate_points(chunk, name="map"))
    points = validate_points(chunk.points, name="map")
    return PointCloud(points, validate_attributes(chunk.attributes, len(points), name="map"), chunk.metadata)


def _model_list(model) -> tuple[list, np.ndarray]:
    """The models to try (one, or each of a list) and their common tile size (metres)."""
    models = list(model) if isinstance(model, (list, tuple)) else [model]
    if not models:
        raise MapsqueezeError("no model to compress with")
    sizes = {tuple(float(v) for v in m.config.tile_size) for m in models}
    if len(sizes) > 1:
        raise MapsqueezeError(f"the models to choose from have different tile sizes: {sorted(sizes)}")
    return models, np.asarray(sizes.pop(), dtype=np.float64)


def check_refine_steps(steps: int) -> None:
    """MapsqueezeError unless steps is an integer from 0 to MAX_REFINE_STEPS."""
    if isinstance(steps, bool) or not isinstance(steps, (int, np.integer)) or not 0 <= steps <= MAX_REFINE_STEPS:
        raise MapsqueezeError(f"refinement steps must be an integer from 0 to {MAX_REFINE_STEPS}, got {steps!r}")


def _check_tile_size(index: tuple[int, int, int], n_points: int) -> None:
    if n_points > MAX_POINTS_PER_TILE:
        raise InvalidPointCloudError(
            f"tile {index} holds {n_points:,} points, more than the {MAX_POINTS_PER_TILE:,} a tile may hold")


def _spill_name(index: tuple[int, int, int], attribute: int | None = None) -> str:
    """Spill file of a tile's float64 points, or of its attribute number `attribute`."""
    suffix = "f64" if attribute is None else f"a{attribute}"
    return "tile_{}_{}_{}.{}".format(*index, suffix)


def _compress_tiles(
    tile_source: Callable[[], Iterable[tuple[tuple[int, int, int], np.ndarray]]],
    n_tiles: int,
    n_points: int,
    origin: np.ndarray,
    models: list,
    precision: Precision,
    position_step_m: float | None,
    feature_step_std: float,
    progress: ProgressCallback | None,
    refine_steps: int,
    target: RateTarget,
    schema: AttributeSchema | None = None,
    workers: int | None = 1,
    dask_scheduler: str | None = None,
) -> bytes:
    """Encode (tile index, its float64 world points, its attributes) triples, given in tile order by each call of
    tile_source(), with each model in turn; keep the model whose per-tile choices (`codec.modes`) suit the target
    best; assemble (with an attribute section when `schema` is given)."""
    best = None
    for position, model in enumerate(models):
        def tile_progress(done: int, total: int, offset: int = position * n_tiles) -> None:
            if progress:
                progress(offset + done, len(models) * n_tiles)

        encoded = _encode_tiles(tile_source(), n_tiles, origin, model, refine_steps, target, workers,
                                dask_scheduler, tile_progress)
        streams = AttributeCoder(tile_source, model, schema, workers, dask_scheduler)
        latent = _code_network_candidates(encoded, model, precision, position_step_m, feature_step_std)
        weights = [tile.n_points for tile in encoded]
        if target.bpp is None:
            choices = [choose_for_error(tile.candidates, target.max_error_m) if target.max_error_m is not None
                       else choose(tile.candidates, _network_bytes(tile)) for tile in encoded]
            per_patch = (PatchChooser(tile_source, workers, dask_scheduler, WORKER_MODULES)
                         if target.post_filter == "patch" and not target.given else None)
            data = _assemble(encoded, choices, model, latent, origin, n_points, streams, per_patch)
        else:  # the payload budget is what the file may hold less the header and table of the last attempt
            target_bytes = target.bpp * n_points / 8
            budget = target_bytes
            for _ in range(_RATE_ATTEMPTS):
                choices = choose_for_rate([tile.candidates for tile in encoded], weights, budget)
                data = _assemble(encoded, choices, model, latent, origin, n_points, streams)
                if len(data) <= target_bytes:
                    break
                budget -= len(data) - target_bytes
        mean_d_e = summary(weights, choices)[1]
        score = ((len(data) > target.bpp * n_points / 8, mean_d_e) if target.bpp is not None
                 else (len(data), mean_d_e))
        if best is None or score < best[0]:
            best = (score, data)
    return best[1]


_RATE_ATTEMPTS = 4
"""Choices tried under a --bpp budget, each with the payload budget shrunk by the previous file's excess."""


def _assemble(encoded: list[_EncodedTile], choices: list[Candidate], model, latent: LatentCodec,
              origin: np.ndarray, n_points: int, attributes: AttributeCoder,
              patch_chooser: PatchChooser | None = None) -> bytes:
    """The container of the chosen codings (the latent codec refitted over the tiles that kept the network), with
    the attribute section `attributes` codes on their decoded geometry; with patch choices where they pay when a
    `patch_chooser` is given."""
    for tile, choice in zip(encoded, choices):
        tile.choice = choice
    latent = _recode_chosen(encoded, latent)
    if patch_chooser is not None:
        patch_chooser(encoded, model, latent, origin)
    layout = latent.layout
    header = Header(
        model_id=model.model_id,
        weights_sha256=model.weights_sha256,
        precision=latent.precision,
        subsampling_dist_m=layout.subsampling_dist_m,
        tile_size=layout.tile_size,
        origin=tuple(float(v) for v in origin),
        n_points=n_points,
        n_tiles=len(encoded),
        n_features=layout.n_features,
        raw_step_m=RAW_STEP_M,
        latent=latent,
        default_count=DefaultCount.native,
    )
    records = [tile.record() for tile in encoded]
    geometry = serialise_container(header, records)
    if attributes.schema is None:
        return geometry
    section = AttributeSection(attributes.schema, attributes.streams(geometry, [tile.choice for tile in encoded]))
    return serialise_container(header, records, section)


@dataclass(frozen=True)
class _TileJob:
    """What every tile's encoding shares (sent once to each worker)."""

    model: object
    origin: np.ndarray  # float64 world corner of the tile grid (metres)
    tile_size: np.ndarray
    refine_steps: int
    target: RateTarget


def _encode_job(job: _TileJob, item: tuple[tuple[int, int, int], np.ndarray, dict]) -> _EncodedTile:
    """One tile's job: (tile index, its float64 world points, its attributes) -> its embedding and classical
    candidates (attributes are coded once the tile's coding is chosen, `codec.tileattributes`)."""
    index, points, _ = item
    tile_origin = job.origin + np.asarray(index) * job.tile_size
    return _encode_tile(index, tile_origin, points, job.tile_size, job.model, job.refine_steps, job.target)


def _network_bytes(tile: _EncodedTile) -> int | None:
    network = [c for c in tile.candidates if c.coding is TileCoding.network]
    return network[0].n_bytes if network else None


def _encode_tiles(tile_points: Iterable[tuple[tuple[int, int, int], np.ndarray, dict]], n_tiles: int,
                  origin: np.ndarray, model, refine_steps: int, target: RateTarget, workers: int | None,
                  dask_scheduler: str | None, progress: ProgressCallback) -> list[_EncodedTile]:
    """Every tile's candidates with one model, encoded by `workers` processes or a Dask cluster (`codec.executor`)."""
    tile_size = np.asarray(model.config.tile_size, dtype=np.float64)
    encoded = []
    job = _TileJob(model, origin, tile_size, refine_steps, target)
    executor = open_executor(workers, dask_scheduler, job, n_tiles, WORKER_MODULES)
    try:
        for done, tile in enumerate(executor.map(_encode_job, job, tile_points), start=1):
            encoded.append(tile)
            progress(done, n_tiles)
    finally:
        executor.close(abort=sys.exc_info()[0] is not None)
    return encoded


def _encode_tile(index: tuple[int, int, int], tile_origin: np.ndarray, tile_points: np.ndarray,
                 tile_size: np.ndarray, model, refine_steps: int, target: RateTarget = RateTarget()) -> _EncodedTile:
    """The tile's embedding and its classical candidates, each with its payload and D_e: raw when the tile is sparse
    enough for raw coding to compete or a rate target is given, the octree at each leaf of OCTREE_LEAVES_M unless
    the target forbids the fallback; the network's decode post-filter setting (chosen on the decode of the
    unquantised embedding, none under post-filter "off") and the network's D_e: that of the filtered decode, except
    under the default patch planes without a rate target, where it is the unfiltered decode's (the filter moves D_e
    by -2 to +5 % on the real submaps; this spares a nearest-neighbour search over 2-3 times the points, and the
    tiles' codings are those of post-filter "off"). D_e values are `codec.distortion`'s: estimated on samples, exact
    where two are close, exact throughout under a rate target or with the neighbour-plane post-filter ("auto")."""
    _check_tile_size(index, len(tile_points))
    lo, hi = quantise_bounds(tile_points - tile_origin, tile_size)
    local = to_local(tile_points, frame_origin(tile_origin, lo, tile_size), tile_size)
    extent = np.subtract(hi, lo) * tile_size / BOUNDS_STEPS
    embedding = model.encode(local)
    n_embedding = len(embedding.points)
    distortion = CandidateDistortion(local, exact=target.given or target.post_filter == "auto")
    classical = []  # (coding, payload, label) in the order their decodings were added to `distortion`
    if target.given or len(local) <= RAW_CANDIDATE_POINTS_PER_EMBEDDING * n_embedding:
        raw = encode_raw_tile(local, tile_size)
        distortion.add(decode_raw_tile(raw, tile_size, len(local), "raw candidate"))
        classical.append((TileCoding.raw, raw, "raw"))
    if len(local) <= RAW_POINTS_PER_EMBEDDING * n_embedding:  # too sparse for the network and the octree
        return _EncodedTile(index, len(local), lo, hi, extent, None, None, _candidates(classical, distortion.settle()))
    leaves = OCTREE_LEAVES_M if target.fallback else ()
    for leaf, (payload, centres) in zip(leaves, encode_octree_tiles(local, tile_size, leaves)):
        distortion.add(octree_points(centres, extent, None),
                       lambda points, leaf=leaf: own_leaf_distances(points, tile_size, leaf, extent))
        classical.append((TileCoding.octree, payload, f"octree {leaf:g} m"))
    if refine_steps:
        embedding = model.refine(local, embedding, refine_steps)
    post_filter = OFF
    if target.post_filter == "auto":
        post_filter, network_d_e = choose_post_filter(
            local, network_points(model, embedding.points, embedding.features, extent, None),
            frame_origin(tile_origin, lo, tile_size), lambda cloud: keep_inside(cloud, extent))
        d_e = distortion.settle()
    else:
        if target.post_filter == "patch":
            frame = frame_origin(tile_origin, lo, tile_size)
            uncropped = model.decode(embedding.points, embedding.features)
            decoded = keep_inside(uncropped, extent)
            post_filter, filtered = choose_patch_filter(local + frame, uncropped, decoded,
                                                        model.config.upsampling_factors, frame, extent)
            if target.given:
                decoded = filtered
        else:
            decoded = network_points(model, embedding.points, embedding.features, extent, None)
        distortion.add(decoded)
        *d_e, network_d_e = distortion.settle()
    return _EncodedTile(index, len(local), lo, hi, extent, embedding.points, embedding.features,
                        _candidates(classical, d_e), network_d_e, post_filter)


def _candidates(classical: list[tuple[TileCoding, bytes, str]], d_e: list[float]) -> list[Candidate]:
    return [Candidate(coding, payload, len(payload), value, label)
            for (coding, payload, label), value in zip(classical, d_e)]


def _code_network_candidates(encoded: list[_EncodedTile], model, precision: Precision, position_step_m: float | None,
                             feature_step_std: float) -> LatentCodec:
    """Code every network tile with the precision's latent codec fitted over all of them (q: quantiser and
    histograms) and add its candidate: the payload's size and the D_e of the network's output for the unquantised
    embedding, measured while the tile was in memory (the embedding coding adds a few per cent to it, BENCHMARKS.md
    "Quantiser steps")."""
    network_tiles = [tile for tile in encoded if tile.points is not None]
    layout = LatentLayout(float(model.config.subsampling_dist), tuple(float(v) for v in model.config.tile_size),
                          int(model.config.embedding_dim))
    latent = LATENT_CODECS[precision].fit([(tile.points, tile.features) for tile in network_tiles], layout,
                                          position_step_m=position_step_m, feature_step_std=feature_step_std)
    for tile in network_tiles:
        payload = latent.encode(tile.points, tile.features)
        tile.candidates.append(Candidate(TileCoding.network, payload, len(payload), tile.network_d_e, "network"))
    return latent


def _recode_chosen(encoded: list[_EncodedTile], latent: LatentCodec) -> LatentCodec:
    """Refit the latent codec over the tiles that kept the network (`LatentCodec.refit`: same quantisation, so the
    same decoded points) and code those tiles with it."""
    chosen = [tile for tile in encoded if tile.choice.coding is TileCoding.network]
    refitted = latent.refit([(tile.points, tile.features) for tile in chosen])
    for tile in chosen:
        payload = refitted.encode(tile.points, tile.features)
        tile.choice = Candidate(TileCoding.network, payload, len(payload), tile.choice.d_e, tile.choice.label)
    return refitted
