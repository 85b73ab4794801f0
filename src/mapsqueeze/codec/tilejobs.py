"""The per-tile jobs of compress (`codec.compress`), run by its pool threads or a Dask cluster
(`codec.executor`): `embed_job` encodes a tile, `candidates_job` (once the map's latent codec is fitted over every
tile's embedding) gives its candidate codings with their D_e, the network's decode post-filter and patch-choice
search, on one decode of the tile's coded embedding, as the decoder will see it."""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np

from mapsqueeze.codec.container import (
    BOUNDS_STEPS, DEFAULT_MAX_TILE_POINTS, MAX_POINTS_PER_TILE, TileCoding, frame_origin, quantise_bounds,
)
from mapsqueeze.codec.distortion import CandidateDistortion
from mapsqueeze.codec.entropy import ByteReader
from mapsqueeze.codec.latent import LATENT_CODECS
from mapsqueeze.codec.modes import Candidate, RateTarget
from mapsqueeze.codec.octreetile import OCTREE_LEAVES_M, encode_octree_tiles, own_leaf_distances
from mapsqueeze.codec.postfilter import (
    CHOICE_SEARCH_START,
    OFF,
    PatchChoiceSearch,
    PostFilter,
    apply_patch_filter,
    choices_pay_clearly,
    choose_patch_filter,
    choose_post_filter,
    search_patch_choices,
)
from mapsqueeze.codec.rawtile import decode_raw_tile, encode_raw_tile
from mapsqueeze.codec.tilepoints import keep_inside, network_points, octree_points
from mapsqueeze.errors import InvalidPointCloudError, MapsqueezeError, TileLimitWarning
from mapsqueeze.geometry.bounds import bounding_box
from mapsqueeze.geometry.tiling import to_local

RAW_POINTS_PER_EMBEDDING = 4
"""A tile with at most this many points per embedding point is coded raw: the decoder, trained to grow each
embedding point into hundreds of points of a dense surface, fits such sparse tiles poorly."""

RAW_CANDIDATE_POINTS_PER_EMBEDDING = 20
"""Raw coding is also tried (and kept when smaller) for tiles with up to this many points per embedding point;
beyond it raw coding (>= 13 bits a point) cannot beat even f32 embeddings (192 bits per embedding point)."""


@dataclass
class EncodedTile:
    """One tile while the map is being compressed: its table fields, embedding and candidate codings."""

    index: tuple[int, int, int]
    n_points: int
    bounds_lo: tuple[int, int, int]
    bounds_hi: tuple[int, int, int]
    extent_m: np.ndarray  # size of the tile's bounds box (metres)
    n_embedding: int  # the encoder's embedding points
    points: np.ndarray | None  # network embedding (None when the network is no candidate, or not the tile's choice)
    features: np.ndarray | None
    candidates: list[Candidate] | None = None  # set by `compress._tile_candidates` (the network's last; without a
    # rate budget only the chosen one)
    post_filter: int = OFF  # the network output's decode post-filter (`codec.postfilter`)
    patch_choices: PatchChoiceSearch | None = None  # the search's result on the network's decode, when run
    choice: Candidate | None = None


def warn_of_tile_limit(encoded: list[EncodedTile], post_filters: list[int], model) -> None:
    """A TileLimitWarning when a tile would decode to more than DEFAULT_MAX_TILE_POINTS points, which decompress
    refuses unless --max-tile-points allows it: a network tile's native count (its embedding points x the upsampling
    factors x its post-filter's copies, `post_filters`: the written ones, what the decoder computes whole), and any
    tile's input count (version 1's default; what `--points` splits by), whichever is larger."""
    factor = int(np.prod(model.config.upsampling_factors))
    counts = {}
    for tile, post_filter in zip(encoded, post_filters):
        native = 0
        if tile.choice.coding is TileCoding.network and tile.points is not None:
            native = len(tile.points) * factor * (1 + PostFilter.parse(post_filter).spread_copies)
        counts[tile.index] = max(native, tile.n_points)
    over = {index: count for index, count in counts.items() if count > DEFAULT_MAX_TILE_POINTS}
    if over:
        index, count = max(over.items(), key=lambda item: item[1])
        tiles = "1 tile decodes" if len(over) == 1 else f"{len(over):,} tiles decode"
        warnings.warn(TileLimitWarning(
            f"{tiles} to more than the {DEFAULT_MAX_TILE_POINTS:,} points per tile that decompress and view allow "
            f"by default (tile {index}: {count:,}); decompress or view with --max-tile-points {count} (API: "
            "max_tile_points=)"), stacklevel=3)


def check_tile_size(index: tuple[int, int, int], n_points: int) -> None:
    if n_points > MAX_POINTS_PER_TILE:
        raise InvalidPointCloudError(
            f"tile {index} holds {n_points:,} points, more than the {MAX_POINTS_PER_TILE:,} a tile may hold")


@dataclass(frozen=True)
class TileJob:
    """What every tile's encoding shares (sent once to each worker)."""

    model: object
    origin: np.ndarray  # float64 world corner of the tile grid (metres)
    tile_size: np.ndarray
    refine_steps: int = 0
    target: RateTarget = RateTarget()
    latent: tuple | None = None  # the latent codec (precision, layout, `LatentCodec.write`'s state)
    compiled: bool = True  # False: numpy's versions of the compiled kernels (the same bytes, no numba loaded)


def _tile_frame(job: TileJob, index: tuple[int, int, int], points: np.ndarray
                ) -> tuple[tuple[int, int, int], tuple[int, int, int], np.ndarray, np.ndarray, np.ndarray]:
    """(bounds_lo, bounds_hi, extent in metres, frame origin in world metres, float64 tile-local points) of a
    tile's float64 world points."""
    check_tile_size(index, len(points))
    tile_origin = job.origin + np.asarray(index) * job.tile_size
    # the box of points - tile_origin is its corners' (a subtraction rounds monotonically): no (N, 3) temporary
    lo, hi = quantise_bounds(np.stack(bounding_box(points)) - tile_origin, job.tile_size)
    frame = frame_origin(tile_origin, lo, job.tile_size)
    return lo, hi, np.subtract(hi, lo) * job.tile_size / BOUNDS_STEPS, frame, to_local(points, frame, job.tile_size)


def embed_job(job: TileJob, item: tuple[tuple[int, int, int], np.ndarray, dict]) -> EncodedTile:
    """One tile's first job: (tile index, its float64 world points, its attributes) -> its table fields and the
    network's embedding (refined when asked), or none when the tile is too sparse for the network."""
    index, points, _ = item
    lo, hi, extent, _, local = _tile_frame(job, index, points)
    embedding = job.model.encode(local, compiled=job.compiled)
    n_embedding = len(embedding.points)
    if len(local) <= RAW_POINTS_PER_EMBEDDING * n_embedding:  # too sparse for the network and the octree
        return EncodedTile(index, len(local), lo, hi, extent, n_embedding, None, None)
    if job.refine_steps:
        embedding = job.model.refine(local, embedding, job.refine_steps)
    return EncodedTile(index, len(local), lo, hi, extent, n_embedding, embedding.points, embedding.features)


def candidates_job(job: TileJob, item: tuple) -> tuple:
    """One tile's second job: (encoded index, embedding points, network payload or None, given index, float64
    world points) -> (classical candidates, the network's D_e, its post-filter, its patch-choice search or None)."""
    expected, n_embedding, payload, index, points = item
    if tuple(index) != tuple(expected):
        raise MapsqueezeError(f"tile {tuple(index)} given where tile {tuple(expected)} was encoded")
    embedding = None
    if payload is not None:
        precision, layout, state = job.latent
        latent = LATENT_CODECS[precision].read(ByteReader(state, "latent codec"), layout)
        embedding = latent.decode(payload, len(points), f"tile {tuple(index)}")
    return _encode_tile(index, points, job, n_embedding, embedding, None if payload is None else len(payload))


def _encode_tile(index: tuple[int, int, int], tile_points: np.ndarray, job: TileJob, n_embedding: int,
                 embedding: tuple[np.ndarray, np.ndarray] | None, network_bytes: int | None) -> tuple:
    """The tile's classical candidates, each with its payload and D_e, and the network's D_e, decode post-filter
    and patch-choice search for `embedding` (None: no network candidate) as the decoder sees it (coded with the
    map's latent codec): raw when the tile is sparse enough for raw coding to compete or a rate target is given,
    the octree at each leaf of OCTREE_LEAVES_M unless the target forbids the fallback (without a target, none of
    the leaves finer than the first whose payload exceeds the network's, `encode_octree_tiles`); the network's decode
    post-filter setting (none under post-filter "off") and the network's D_e: that of the filtered decode, except
    under the default patch planes without a rate target, where it is the unfiltered decode's (the filter moves D_e
    by -2 to +5 % on the real submaps; this spares a nearest-neighbour search over 2-3 times the points, and the
    tiles' codings are those of post-filter "off"), where the patch choices are also searched on the decode
    (`_patch_choices`, kept by `_assemble` where they pay). D_e values are `codec.distortion`'s:
    without a target, NaN for the classical candidates the mode decision cannot pick (larger than the network's
    payload of `network_bytes`, `modes.choose`: neither decoded nor searched); estimated on samples, exact where
    two it may pick are close; exact throughout under a rate target or with the neighbour-plane post-filter
    ("auto")."""
    model, target, tile_size = job.model, job.target, job.tile_size
    lo, _, extent, frame, local = _tile_frame(job, index, tile_points)
    distortion = CandidateDistortion(local, exact=target.given or target.post_filter == "auto", compiled=job.compiled)

    def competing(payload: bytes) -> bool:  # the default rule picks among the candidates no larger than the network
        return target.given or network_bytes is None or len(payload) <= network_bytes

    classical = []  # (coding, payload, label) in the order their decodings were added to `distortion`
    if target.given or len(local) <= RAW_CANDIDATE_POINTS_PER_EMBEDDING * n_embedding:
        raw = encode_raw_tile(local, tile_size)
        distortion.add(lambda: decode_raw_tile(raw, tile_size, len(local), "raw candidate"), competing=competing(raw))
        classical.append((TileCoding.raw, raw, "raw"))
    if embedding is None:
        return _candidates(classical, distortion.settle()), None, OFF, None
    leaves = OCTREE_LEAVES_M if target.fallback else ()
    octrees = encode_octree_tiles(local, tile_size, leaves, None if target.given else network_bytes)
    for leaf, payload, centres in octrees:
        distortion.add(lambda centres=centres: octree_points(centres, extent, None),
                       lambda points, leaf=leaf: own_leaf_distances(points, tile_size, leaf, extent, job.compiled),
                       competing(payload))
        classical.append((TileCoding.octree, payload, f"octree {leaf:g} m"))
    post_filter, search = OFF, None
    if target.post_filter == "auto":
        post_filter, network_d_e = choose_post_filter(local, network_points(model, *embedding, extent, None), frame,
                                                      lambda cloud: keep_inside(cloud, extent, job.compiled))
        d_e = distortion.settle()
    else:
        if target.post_filter == "patch":
            uncropped = model.decode(*embedding)
            decoded = keep_inside(uncropped, extent, job.compiled)
            if target.given:
                post_filter = choose_patch_filter(local + frame, uncropped, decoded, model.config.upsampling_factors,
                                                  frame, extent, job.compiled)
                if post_filter != OFF:
                    decoded = apply_patch_filter(uncropped, post_filter, model.config.upsampling_factors, extent,
                                                 compiled=job.compiled)
        else:
            decoded = network_points(model, *embedding, extent, None)
        distortion.add(decoded)
        *d_e, network_d_e = distortion.settle()
        if target.post_filter == "patch" and not target.given:
            del distortion, decoded  # the candidates' decodes and trees: the search's arrays take their memory
            post_filter, search = _patch_choices(tile_points, local, frame, extent, uncropped, model, network_bytes,
                                                 job.compiled)
    return _candidates(classical, d_e), network_d_e, post_filter, search


def _patch_choices(tile_points: np.ndarray, local: np.ndarray, frame: np.ndarray, extent: np.ndarray,
                   uncropped: np.ndarray, model, network_bytes: int, compiled: bool
                   ) -> tuple[int, PatchChoiceSearch | None]:
    """(patch-plane setting, patch-choice search or None) of a network tile under the default post-filter without a
    rate target: the choices searched from the option of CHOICE_SEARCH_START; only where they do not pay clearly
    (`postfilter.choices_pay_clearly`) the tile's own setting (`choose_patch_filter`, what `_assemble` stores where
    the choices do not pay) and, where it differs, the search again from its option. tile_points: the tile's
    float64 world points; local: their tile-local float32 metres relative to the world point `frame`; uncropped:
    the network's whole decode of the embedding the file holds."""
    factors = model.config.upsampling_factors

    def search_from(setting: int):
        return search_patch_choices(np.asarray(tile_points, dtype=np.float64), uncropped, factors, frame, extent,
                                    setting, model.config.patch_choice_copy_weight, network_bytes, compiled)

    search = search_from(CHOICE_SEARCH_START)
    if choices_pay_clearly(search, network_bytes):
        return CHOICE_SEARCH_START, search
    setting = choose_patch_filter(local + frame, uncropped, keep_inside(uncropped, extent, compiled), factors, frame,
                                  extent, compiled)
    return setting, (search if setting == CHOICE_SEARCH_START or search is None else search_from(setting))


def _candidates(classical: list[tuple[TileCoding, bytes, str]], d_e: list[float]) -> list[Candidate]:
    return [Candidate(coding, payload, len(payload), value, label)
            for (coding, payload, label), value in zip(classical, d_e)]
