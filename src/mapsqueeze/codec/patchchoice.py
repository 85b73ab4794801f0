"""Patch choices for the tiles of a map being compressed (`postfilter.choose_patch_choices`), searched once the
tiles' codings are chosen, on the decode of each network tile's embedding as the file codes it."""

from __future__ import annotations

import sys
from collections.abc import Callable, Iterable
from dataclasses import dataclass

import numpy as np

from mapsqueeze.codec.container import TileCoding, frame_origin
from mapsqueeze.codec.entropy import ByteReader, ByteWriter
from mapsqueeze.codec.executor import open_executor
from mapsqueeze.codec.latent import LATENT_CODECS, LatentCodec
from mapsqueeze.codec.modes import Candidate
from mapsqueeze.codec.postfilter import PATCH_CHOICES, choose_patch_choices, encode_patch_choices
from mapsqueeze.errors import MapsqueezeError


@dataclass(frozen=True)
class PatchChooser:
    """Searches patch choices (`postfilter.choose_patch_choices`) for each tile that kept the network, on the decode
    of its embedding as the file codes it (in the decoder's order), by `workers` processes or a Dask cluster; where
    they pay, the tile's post-filter becomes PATCH_CHOICES and the choice stream is put before its payload. The
    mode decision was made on the payload without the stream (it adds 7-10 % to the file on the real submaps)."""

    tile_source: Callable[[], Iterable[tuple[tuple[int, int, int], np.ndarray, dict]]]
    workers: int | None
    dask_scheduler: str | None
    preload: tuple[str, ...]  # modules the worker processes import (`executor.ProcessExecutor`)

    def __call__(self, encoded: list, model, latent: LatentCodec, origin: np.ndarray) -> None:
        """Add patch choices to `encoded` (compress's tiles: index, bounds_lo, extent_m, post_filter, choice) in
        place."""
        network = [position for position, tile in enumerate(encoded) if tile.choice.coding is TileCoding.network]
        wanted = set(network)
        items = ((encoded[position].index, index, encoded[position].bounds_lo, encoded[position].extent_m,
                  encoded[position].post_filter, encoded[position].choice.payload, points)
                 for position, (index, points, _) in enumerate(self.tile_source()) if position in wanted)
        state = ByteWriter()  # the codec as the header stores it (its entropy models do not pickle)
        latent.write(state)
        context = (model, latent.precision, latent.layout, state.getvalue(), origin)
        executor = open_executor(self.workers, self.dask_scheduler, context, len(network), self.preload)
        try:
            for position, choices in zip(network, executor.map(_patch_choice_job, context, items)):
                if choices is not None:
                    tile = encoded[position]
                    payload = encode_patch_choices(choices) + tile.choice.payload
                    tile.post_filter = PATCH_CHOICES
                    tile.choice = Candidate(TileCoding.network, payload, len(payload), tile.choice.d_e,
                                            tile.choice.label)
        finally:
            executor.close(abort=sys.exc_info()[0] is not None)


def _patch_choice_job(context: tuple, item: tuple) -> np.ndarray | None:
    """One tile's patch choices or None: (encoded index, given index, bounds_lo, extent_m, post-filter setting,
    latent payload, float64 world points); context: the model, the latent codec's precision, layout and state
    (`LatentCodec.write`) and the grid's origin."""
    model, precision, layout, state, origin = context
    latent = LATENT_CODECS[precision].read(ByteReader(state, "latent codec"), layout)
    expected, index, bounds_lo, extent, post_filter, payload, points = item
    if tuple(index) != tuple(expected):
        raise MapsqueezeError(f"tile {tuple(index)} given where tile {tuple(expected)} was encoded")
    tile_size = np.asarray(model.config.tile_size, dtype=np.float64)
    embedding_points, features = latent.decode(payload, len(points), f"tile {tuple(index)}")
    frame = frame_origin(origin + np.asarray(index) * tile_size, bounds_lo, tile_size)
    return choose_patch_choices(np.asarray(points, dtype=np.float64), model.decode(embedding_points, features),
                                model.config.upsampling_factors, frame, extent, post_filter, len(payload))
