"""Whole map -> .msq bytes: tile the map, store each occupied tile with the coding its mode decision picks (the
network's embedding, raw points or an octree; `codec.modes`), pack."""

from __future__ import annotations

import importlib
import os
import sys
import threading
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass

import numpy as np

from mapsqueeze.codec.attributes import (
    DEFAULT_RELATIVE_STEP,
    DEFAULT_VOXEL_M,
    AttributeSchema,
    ValueRange,
    build_schema,
    check_resolution,
    parse_selection,
)
from mapsqueeze.codec.container import (
    AttributeSection,
    TileCoding,
    TileRecord,
    serialise_container,
)
from mapsqueeze.codec.embedding import DEFAULT_FEATURE_STEP_STD, Precision
from mapsqueeze.codec.entropy import ByteWriter
from mapsqueeze.codec.executor import ProgressCallback, default_workers, open_executor
from mapsqueeze.codec.header import DefaultCount, Header
from mapsqueeze.codec.latent import LATENT_CODECS, LatentCodec, LatentLayout
from mapsqueeze.codec.modes import Candidate, RateTarget, choose, choose_for_error, choose_for_rate, summary
from mapsqueeze.codec.postfilter import OFF, PATCH_CHOICES, patch_choice_prefix
from mapsqueeze.codec.rawtile import RAW_STEP_M
from mapsqueeze.codec.tileattributes import AttributeCoder
from mapsqueeze.codec.tilejobs import (
    EncodedTile, TileJob, candidates_job, check_tile_size, embed_job, warn_of_tile_limit,
)
from mapsqueeze.errors import InvalidPointCloudError, MapsqueezeError
from mapsqueeze.geometry.bounds import bounding_box
from mapsqueeze.geometry.tiling import fit_grid, tile_map
from mapsqueeze.geometry.validation import validate_points
from mapsqueeze.io import PointCloud, validate_attributes, work_dir

MAX_REFINE_STEPS = 10_000
"""Encode-time refinement steps accepted at most per tile (`CompressionModel.refine`; a guard against typos)."""

NUMPY_KERNEL_POINTS = 15_000
"""Maps of at most this many points are encoded with numpy's versions of the compiled kernels (`TileJob.compiled`
False; the same bytes): loading numba costs a process 0.5-0.6 CPU-s, more than numpy's versions spend on such
maps (BENCHMARKS.md "Where a small compress spends its start-up")."""


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

    def __post_init__(self) -> None:
        check_resolution(self.voxel_m, self.relative_step)  # an error whether or not the map has attributes


def _attribute_schema(ranges: dict[str, ValueRange], metadata: dict | None,
                      options: AttributeOptions) -> AttributeSchema | None:
    """The schema of the selected attributes, or None when there is nothing to code (a geometry-only file)."""
    names = parse_selection(options.selection, list(ranges))
    if not names and not metadata:
        return None
    return build_schema({name: ranges[name] for name in names}, options.voxel_m, options.relative_step,
                        metadata or {})


def _ranges(attributes: dict[str, np.ndarray]) -> dict[str, ValueRange]:
    return {name: ValueRange.of(values) for name, values in attributes.items()}


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
    (`CompressionModel.refine`: slower encoding, lower D_e, same format). Tiles are encoded by `workers` threads
    (None: one per core) or on the Dask cluster at `dask_scheduler` ("local" starts one; `codec.executor`); only
    their compact embeddings and payloads are kept until the file is assembled (q fits its histograms over all tiles
    before coding them). Deterministic: the same points, model and settings give the same bytes, whatever runs them.
    attributes (name -> (N,) values) selected by attribute_options are coded per tile after the geometry, and
    metadata (JSON-serialisable, e.g. the LAS header's) is stored; with neither the file is geometry-only.
    """
    check_refine_steps(refine_steps)
    models, tile_size = _model_list(model)
    points = validate_points(points, name="map")
    kernels = _load_kernels_meanwhile(dask_scheduler) if len(points) > NUMPY_KERNEL_POINTS else None
    attributes = validate_attributes(attributes, len(points), name="map")
    schema = _attribute_schema(_ranges(attributes), metadata, attribute_options)
    origin, shape = fit_grid(*bounding_box(points), tile_size)
    tiles = tile_map(points, tile_size, origin=origin, shape=shape)
    coded = [spec.name for spec in schema.specs] if schema else []
    if kernels:
        kernels.join()

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
    temporary directory (in spill_dir, default the system's; 24 bytes a point plus the attributes) and hands each
    tile, read back, to the encoding workers as soon as no later chunk's bounding box (from pass 1) reaches it: a
    map whose file holds it region by region is encoded as it is read (memory: a chunk and one tile per worker).
    """
    check_refine_steps(refine_steps)
    models, tile_size = _model_list(model)
    kernels = None
    lowest, highest, n_points = np.full(3, np.inf), np.full(3, -np.inf), 0
    ranges: dict[str, ValueRange] = {}
    metadata = None
    boxes = []  # each chunk's bounding box
    for chunk in _checked_clouds(chunks()):
        chunk_low, chunk_high = bounding_box(chunk.points)
        boxes.append((chunk_low, chunk_high))
        lowest, highest = np.minimum(lowest, chunk_low), np.maximum(highest, chunk_high)
        metadata = chunk.metadata if metadata is None else metadata
        for name, value_range in _ranges(chunk.attributes).items():
            ranges[name] = ranges[name].merge(value_range) if name in ranges else value_range
        n_points += len(chunk)
        if kernels is None and n_points > NUMPY_KERNEL_POINTS:  # a map the compiled kernels encode
            kernels = _load_kernels_meanwhile(dask_scheduler)
    if n_points == 0:
        raise InvalidPointCloudError("map: the point cloud is empty")
    schema = _attribute_schema(ranges, metadata, attribute_options)
    coded = [(spec.name, spec.dtype) for spec in schema.specs] if schema else []
    origin, shape = fit_grid(lowest, highest, tile_size)  # the grid compress_map fits to the whole map
    last_chunk = _last_chunks(boxes, origin, shape, tile_size)
    with work_dir("mapsqueeze-tiles-", spill_dir) as spill:
        counts: dict[tuple[int, int, int], int] = {}
        indices: list[tuple[int, int, int]] = []  # the tiles in tile order, once every one is spilled

        def read_back(index):
            return (index, np.fromfile(os.path.join(spill, _spill_name(index)), dtype=np.float64).reshape(-1, 3),
                    {name: np.fromfile(os.path.join(spill, _spill_name(index, column)), dtype=dtype)
                     for column, (name, dtype) in enumerate(coded)})

        def spilled_tiles():
            """Pass 2: append each chunk's tiles to their spill files; yield each tile as soon as no later chunk
            can hold points of it (`_last_chunks`), so that the first tiles are encoded while the map is read."""
            waiting: dict[int, list[tuple[int, int, int]]] = {}  # chunk number -> the tiles complete after it
            done = set()
            for number, chunk in enumerate(_checked_clouds(chunks(), n_points)):
                for tile in tile_map(chunk.points, tile_size, origin=origin, shape=shape):
                    if tile.index in done:
                        raise InvalidPointCloudError("map: the input changed between the two reading passes")
                    with open(os.path.join(spill, _spill_name(tile.index)), "ab") as stream:
                        stream.write(chunk.points[tile.point_indices].tobytes())
                    for column, (name, dtype) in enumerate(coded):
                        with open(os.path.join(spill, _spill_name(tile.index, column)), "ab") as stream:
                            stream.write(np.asarray(chunk.attributes[name], dtype=dtype)[tile.point_indices].tobytes())
                    if tile.index not in counts:
                        waiting.setdefault(max(number, last_chunk(tile.index)), []).append(tile.index)
                    counts[tile.index] = counts.get(tile.index, 0) + len(tile.point_indices)
                complete = sorted(waiting.pop(number, []))
                for index in complete:  # refused before a tile that large is read back into memory
                    check_tile_size(index, counts[index])
                done.update(complete)
                yield from map(read_back, complete)
            if sum(counts.values()) != n_points or waiting:
                raise InvalidPointCloudError("map: the input changed between the two reading passes")
            indices.extend(sorted(counts))  # the order of tile_map: by (i, j, k)
            if kernels:
                kernels.join()

        return _compress_tiles(lambda: map(read_back, indices), int(np.prod(shape)), n_points, origin, models,
                               precision, position_step_m, feature_step_std, progress, refine_steps, target, schema,
                               workers, dask_scheduler, first_tiles=spilled_tiles())


def _last_chunks(boxes: list[tuple[np.ndarray, np.ndarray]], origin: np.ndarray, shape: np.ndarray,
                 tile_size: np.ndarray) -> Callable[[tuple[int, int, int]], int]:
    """index -> the last chunk whose bounding box (`boxes`, in chunk order) reaches tile `index` of the grid
    (`tile_map`'s index of a point is monotonic in each coordinate, so a chunk's tiles lie between those of its
    box's corners); -1 for none."""
    corners = [np.clip(np.floor((np.stack(ends) - origin) / tile_size).astype(np.int64), 0, shape - 1)
               for ends in zip(*boxes)]

    def last(index: tuple[int, int, int]) -> int:
        reached = np.flatnonzero(np.all((corners[0] <= index) & (index <= corners[1]), axis=1))
        return int(reached[-1]) if len(reached) else -1

    return last


ENCODER_KERNEL_MODULES = ("mapsqueeze.geometry.grid", "mapsqueeze.model.influences", "mapsqueeze.geometry.nearest",
                          "mapsqueeze.geometry.cells", "mapsqueeze.geometry.occupancy", "mapsqueeze.baselines.octree")
"""The modules of the compiled kernels the tile jobs call (`codec.tilejobs`), imported where the jobs first need
them (the command line starts without numba)."""


def _load_kernels_meanwhile(dask_scheduler: str | None) -> threading.Thread | None:
    """A started thread that imports ENCODER_KERNEL_MODULES and loads numba's registries (what the first kernel
    call does: ~0.4-0.5 s in all) while this one reads and tiles a map of more than NUMPY_KERNEL_POINTS points
    (started once that many are read), on a core the reading leaves idle; join it
    once the map is read (tiles encoded before, as `compress_chunks` streams them, wait for the modules on Python's
    import locks and for the registries on numba's compiler lock). It does nothing with a single core, on a Dask
    cluster (whose workers import their own; the coordinator would hold numba's memory for nothing) or once the
    modules are loaded (a process that compressed before): None then. What fails here is left to the tile jobs,
    which import the same modules and report it."""
    if dask_scheduler or default_workers() < 2 or all(name in sys.modules for name in ENCODER_KERNEL_MODULES):
        return None
    thread = threading.Thread(target=_load_kernels, name="mapsqueeze-kernels", daemon=True)
    thread.start()
    return thread


def _load_kernels() -> None:
    try:
        for name in ENCODER_KERNEL_MODULES:
            importlib.import_module(name)
        from numba.core.compiler_lock import global_compiler_lock
        from numba.core.registry import cpu_target

        with global_compiler_lock:
            cpu_target.target_context.refresh()
    except Exception:  # noqa: BLE001 - the tile jobs import the same modules and report what fails
        pass


def _checked_clouds(chunks: Iterable, total: int | None = None) -> Iterator[PointCloud]:
    """The chunks of a map of `total` points (None: not yet known) as PointClouds with validated points and
    attributes (bare (n, 3) arrays have none); errors number the points in the map."""
    first = 0
    for chunk in chunks:
        cloud = chunk if isinstance(chunk, PointCloud) else PointCloud(chunk)
        points = validate_points(cloud.points, "map", first, total)
        first += len(points)
        yield PointCloud(points, validate_attributes(cloud.attributes, len(points), name="map"), cloud.metadata)


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
    first_tiles: Iterable[tuple[tuple[int, int, int], np.ndarray, dict]] | None = None,
) -> bytes:
    """Encode (tile index, its float64 world points, its attributes) triples, given in tile order by each call of
    tile_source(), with each model in turn; keep the model whose per-tile choices (`codec.modes`) suit the target
    best; assemble (with an attribute section when `schema` is given). first_tiles: the same triples in any order
    (as a streamed map's tiles are spilled), for the first model's embeddings instead of tile_source(); n_tiles is
    then at least their count (it only sizes the executor)."""
    best = None
    compiled = n_points > NUMPY_KERNEL_POINTS
    for position, model in enumerate(models):
        first = first_tiles is not None and position == 0
        encoded = _embed_tiles(first_tiles if first else tile_source(), n_tiles, origin, model, refine_steps,
                               workers, dask_scheduler, compiled)
        encoded.sort(key=lambda tile: tile.index)  # first_tiles come as they are read
        n_tiles = len(encoded)

        def tile_progress(done: int, total: int, offset: int = position * n_tiles) -> None:
            if progress:
                progress(offset + done, len(models) * n_tiles)

        latent = _fit_latent(encoded, model, precision, position_step_m, feature_step_std)
        _tile_candidates(encoded, tile_source(), origin, model, latent, target, workers, dask_scheduler,
                         tile_progress, compiled)
        streams = AttributeCoder(tile_source, model, schema, workers, dask_scheduler)
        weights = [tile.n_points for tile in encoded]
        if target.bpp is None:  # each tile's choice was made as its candidates came (`_tile_candidates`)
            choices = [tile.choice for tile in encoded]
            data = _assemble(encoded, choices, model, latent, origin, n_points, streams)
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
        if target.bpp is None:
            score = (len(data), mean_d_e)
        elif len(data) <= target.bpp * n_points / 8:  # within the budget: the lowest D_e
            score = (False, mean_d_e)
        else:  # nothing fits (each tile took its cheapest candidate): the smallest file
            score = (True, len(data), mean_d_e)
        if best is None or score < best[0]:
            best = (score, data)
    return best[1]


_RATE_ATTEMPTS = 4
"""Choices tried under a --bpp budget, each with the payload budget shrunk by the previous file's excess."""


def _assemble(encoded: list[EncodedTile], choices: list[Candidate], model, latent: LatentCodec,
              origin: np.ndarray, n_points: int, attributes: AttributeCoder) -> bytes:
    """The container of the chosen codings (the latent codec refitted over the tiles that kept the network), with
    the attribute section `attributes` codes on their decoded geometry; with patch choices where they were searched
    and pay (`postfilter.patch_choice_prefix`: the choice stream put before the tile's payload, its post-filter
    PATCH_CHOICES; the mode decision was made on the payload without the stream, which adds 7-10 % to the file on
    the real submaps)."""
    for tile, choice in zip(encoded, choices):
        tile.choice = choice
    latent = _recode_chosen(encoded, latent)
    records = []
    for tile in encoded:
        choice, post_filter = tile.choice, tile.post_filter
        if choice.coding is TileCoding.network and tile.patch_choices is not None:
            prefix = patch_choice_prefix(tile.patch_choices, choice.n_bytes)
            if prefix is not None:
                payload = prefix + choice.payload
                choice = Candidate(TileCoding.network, payload, len(payload), choice.d_e, choice.label)
                post_filter = PATCH_CHOICES
        records.append(TileRecord(tile.index, tile.n_points, tile.bounds_lo, tile.bounds_hi, choice.coding,
                                  choice.payload, post_filter if choice.coding is TileCoding.network else OFF))
    warn_of_tile_limit(encoded, [record.post_filter for record in records], model)
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
    geometry = serialise_container(header, records)
    if attributes.schema is None:
        return geometry
    section = AttributeSection(attributes.schema, attributes.streams(geometry, [tile.choice for tile in encoded]))
    return serialise_container(header, records, section)


def _embed_tiles(tile_points: Iterable[tuple[tuple[int, int, int], np.ndarray, dict]], n_tiles: int,
                 origin: np.ndarray, model, refine_steps: int, workers: int | None,
                 dask_scheduler: str | None, compiled: bool = True) -> list[EncodedTile]:
    """Every tile's embedding with one model, by `workers` threads or a Dask cluster (`codec.executor`)."""
    job = TileJob(model, origin, np.asarray(model.config.tile_size, dtype=np.float64), refine_steps,
                  compiled=compiled)
    return _run(embed_job, job, tile_points, n_tiles, workers, dask_scheduler, lambda done, total: None)


def _run(function, job: TileJob, items: Iterable, n_jobs: int, workers: int | None, dask_scheduler: str | None,
         progress: ProgressCallback, keep: Callable[[int, object], object] | None = None) -> list:
    """function(job, item) of every item, in order, on the executor `workers` / `dask_scheduler` open; keep:
    (position, result) -> what is kept of each result, applied as it comes (default: all of it)."""
    results = []
    executor = open_executor(workers, dask_scheduler, n_jobs)
    try:
        for done, result in enumerate(executor.map(function, job, items), start=1):
            results.append(result if keep is None else keep(done - 1, result))
            progress(done, n_jobs)
    finally:
        executor.close(abort=sys.exc_info()[0] is not None)
    return results


def _fit_latent(encoded: list[EncodedTile], model, precision: Precision, position_step_m: float | None,
                feature_step_std: float) -> LatentCodec:
    """The precision's latent codec fitted over every network tile's embedding (q: quantiser and histograms)."""
    layout = LatentLayout(float(model.config.subsampling_dist), tuple(float(v) for v in model.config.tile_size),
                          int(model.config.embedding_dim))
    return LATENT_CODECS[precision].fit([(tile.points, tile.features) for tile in encoded if tile.points is not None],
                                        layout, position_step_m=position_step_m, feature_step_std=feature_step_std)


def _tile_candidates(encoded: list[EncodedTile], tile_points: Iterable[tuple[tuple[int, int, int], np.ndarray, dict]],
                     origin: np.ndarray, model, latent: LatentCodec, target: RateTarget, workers: int | None,
                     dask_scheduler: str | None, progress: ProgressCallback, compiled: bool = True) -> None:
    """Every tile's candidate codings (`candidates_job`), set in `encoded` in place: the network's payload is
    coded here with the map-wide `latent` codec, the workers decode it as the decoder will. Without a rate budget
    the mode decision depends on the tile's own candidates alone (`choose`, `choose_for_error`): each tile's choice
    is made as its candidates come, and only the chosen candidate is kept (the embedding and patch choices only for
    a network tile), so that what compress holds per tile stays small."""
    state = ByteWriter()  # the codec as the header stores it (its entropy models do not pickle)
    latent.write(state)
    job = TileJob(model, origin, np.asarray(model.config.tile_size, dtype=np.float64), target=target,
                   latent=(latent.precision, latent.layout, state.getvalue()), compiled=compiled)
    payloads = [None if tile.points is None else latent.encode(tile.points, tile.features) for tile in encoded]
    items = ((tile.index, tile.n_embedding, payload, index, points)
             for tile, payload, (index, points, _) in zip(encoded, payloads, tile_points))

    def keep(position: int, result: tuple) -> None:
        tile, payload = encoded[position], payloads[position]
        candidates, network_d_e, post_filter, search = result
        payloads[position] = None
        if payload is not None:
            candidates.append(Candidate(TileCoding.network, payload, len(payload), network_d_e, "network"))
        tile.candidates, tile.post_filter, tile.patch_choices = candidates, post_filter, search
        if target.bpp is None:
            tile.choice = (choose_for_error(candidates, target.max_error_m) if target.max_error_m is not None
                           else choose(candidates, None if payload is None else len(payload)))
            tile.candidates = [tile.choice]
            if tile.choice.coding is not TileCoding.network:
                tile.points = tile.features = tile.patch_choices = None

    _run(candidates_job, job, items, len(encoded), workers, dask_scheduler, progress, keep)


def _recode_chosen(encoded: list[EncodedTile], latent: LatentCodec) -> LatentCodec:
    """Refit the latent codec over the tiles that kept the network (`LatentCodec.refit`: same quantisation, so the
    same decoded points) and code those tiles with it."""
    chosen = [tile for tile in encoded if tile.choice.coding is TileCoding.network]
    refitted = latent.refit([(tile.points, tile.features) for tile in chosen])
    for tile in chosen:
        payload = refitted.encode(tile.points, tile.features)
        tile.choice = Candidate(TileCoding.network, payload, len(payload), tile.choice.d_e, tile.choice.label)
    return refitted
