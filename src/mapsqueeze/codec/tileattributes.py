"""Attribute streams of a map's tiles on their decoded geometry, coded once the tiles' codings are chosen."""

from __future__ import annotations

import sys
from collections.abc import Callable, Iterable

import numpy as np

from mapsqueeze.codec.attributes import AttributeSchema, encode_tile_attributes
from mapsqueeze.codec.container import open_container
from mapsqueeze.codec.decompress import attribute_support, tile_frame
from mapsqueeze.codec.executor import open_executor
from mapsqueeze.codec.header import Header
from mapsqueeze.geometry.tiling import to_local


class AttributeCoder:
    """Codes every tile's attribute stream on the tile's default decoded geometry: the chosen payload decoded as
    the decoder does (`decompress.decode_payload` at the native count, read back from the geometry container), the
    values taken from the tile's input points (given again, in tile order, by tile_source()). Streams are kept per
    (tile, candidate) across the rate control's attempts: a candidate decodes to the same points whatever the
    attempt (`LatentCodec.refit` keeps the quantisation)."""

    def __init__(self, tile_source: Callable[[], Iterable[tuple]], model, schema: AttributeSchema | None,
                 workers: int | None, dask_scheduler: str | None):
        self.tile_source, self.model, self.schema = tile_source, model, schema
        self.workers, self.dask_scheduler = workers, dask_scheduler
        self._coded: dict[tuple[int, str], bytes] = {}

    def streams(self, geometry: bytes, choices: list[Candidate]) -> list[bytes]:
        if not self.schema.coded:
            return []
        reader, stream = open_container(geometry)
        with stream:
            wanted = [(position, choice.label) for position, choice in enumerate(choices)
                      if (position, choice.label) not in self._coded]
            missing = {position for position, _ in wanted}
            items = ((reader.entries[position], reader.payload(position), reader.entries[position].label(position),
                      points, values)
                     for position, (_, points, values) in enumerate(self.tile_source()) if position in missing)
            context = (reader.header, self.model, self.schema)
            executor = open_executor(self.workers, self.dask_scheduler, len(wanted))
            try:
                for key, coded in zip(wanted, executor.map(_attribute_job, context, items)):
                    self._coded[key] = coded
            finally:
                executor.close(abort=sys.exc_info()[0] is not None)
        return [self._coded[(position, choice.label)] for position, choice in enumerate(choices)]


def _attribute_job(context: tuple[Header, object, AttributeSchema], item: tuple) -> bytes:
    """One tile's attribute stream: (table entry, payload, label, float64 world points, attributes) -> bytes;
    context: the geometry container's header, the model and the schema."""
    header, model, schema = context
    entry, payload, label, points, attributes = item
    tile_size = np.asarray(header.tile_size)
    support = attribute_support(header, entry, payload, model, label)
    local = to_local(points, tile_frame(header, entry), tile_size)
    return encode_tile_attributes(support, local, attributes, schema, tile_size)
