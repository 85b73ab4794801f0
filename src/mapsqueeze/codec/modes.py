"""Per-tile mode decision: each tile is stored with whichever candidate coding suits the user's target best.

Candidates of a tile: the network's embedding (the file's model, refined when asked), raw points (`rawtile`) and the
occupancy octree at each leaf of OCTREE_LEAVES_M (`octreetile`). Each has a rate R (payload bytes; the network's
measured with the map-wide q model fitted over every tile) and a distortion D (the paper's D_e, `metrics.d_euclidean`,
of the tile's points against what the decoder gives by default for that payload). The rules:
- no target: the lowest D among the candidates no larger than the network payload (so a sparse tile, where the
  decoder is weak, gets the classical coding whenever that is better at no more bytes);
- `max_error_m`: the smallest candidate with D <= max_error_m (the lowest D when none meets it);
- `bpp`: the Lagrangian choice min sum(n_t D_t) + lambda sum(R_t), lambda bisected so that the file fits
  bpp x points / 8 bytes (the cheapest choice per tile when nothing fits; among several models, the smallest
  file is then kept, `codec.compress`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from mapsqueeze.codec.container import TileCoding
from mapsqueeze.errors import MapsqueezeError


POST_FILTER_MODES = ("patch", "auto", "off")
"""Decode post-filters the encoder may choose per network tile (`codec.postfilter`): patch planes where they raise
the tile's IoU (the default, ~10 ms per tile), the neighbour-plane settings (auto: seconds per tile), none (off)."""


@dataclass(frozen=True)
class RateTarget:
    """What the user asks for: a D_e budget in metres or a rate budget in bits per point (at most one), whether
    tiles may fall back to the classical octree, and whether network tiles get a decode post-filter."""

    max_error_m: float | None = None
    bpp: float | None = None
    fallback: bool = True  # offer the octree to every tile (False: the network, raw for sparse tiles)
    post_filter: str = "patch"  # decode post-filter per network tile: POST_FILTER_MODES ("off": the paper's decode)

    def __post_init__(self) -> None:
        if self.max_error_m is not None and self.bpp is not None:
            raise MapsqueezeError("give either a maximum error or a bits-per-point budget, not both")
        if self.post_filter not in POST_FILTER_MODES:
            raise MapsqueezeError(f"post-filter must be one of {', '.join(POST_FILTER_MODES)}, "
                                  f"got {self.post_filter!r}")
        for name, value in (("maximum error (metres)", self.max_error_m), ("bits per point", self.bpp)):
            if value is not None and not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
                raise MapsqueezeError(f"{name} must be a positive number, got {value!r}")

    @property
    def given(self) -> bool:
        return self.max_error_m is not None or self.bpp is not None


@dataclass
class Candidate:
    """One way to store a tile: its coding, payload (None for the network until the final q coding), rate, D_e."""

    coding: TileCoding
    payload: bytes | None
    n_bytes: int
    d_e: float  # metres
    label: str  # e.g. "network", "raw", "octree 0.2 m"


def choose(candidates: list[Candidate], budget_bytes: int | None = None) -> Candidate:
    """The default rule: lowest D_e among the candidates of at most `budget_bytes` (the network payload's size;
    None: the smallest candidate's size), ties to the smaller."""
    if budget_bytes is None:
        budget_bytes = min(c.n_bytes for c in candidates)
    affordable = [c for c in candidates if c.n_bytes <= budget_bytes] or [min(candidates, key=lambda c: c.n_bytes)]
    return min(affordable, key=lambda c: (c.d_e, c.n_bytes))


def choose_for_error(candidates: list[Candidate], max_error_m: float) -> Candidate:
    """The smallest candidate with D_e <= max_error_m, else the one with the lowest D_e."""
    meeting = [c for c in candidates if c.d_e <= max_error_m]
    if meeting:
        return min(meeting, key=lambda c: (c.n_bytes, c.d_e))
    return min(candidates, key=lambda c: (c.d_e, c.n_bytes))


def choose_for_rate(tiles: list[list[Candidate]], weights: list[int], budget_bytes: float) -> list[Candidate]:
    """Per tile the candidate minimising weight x D_e + lambda x bytes, with the smallest lambda whose choices fit
    `budget_bytes` in all (weights: the tiles' point counts, so the sum approximates the map's D_e x points)."""

    def pick(lam: float) -> list[Candidate]:
        return [min(cands, key=lambda c: (w * c.d_e + lam * c.n_bytes, c.n_bytes)) for cands, w in zip(tiles, weights)]

    def total(choice: list[Candidate]) -> int:
        return sum(c.n_bytes for c in choice)

    low, high = 0.0, 1.0
    if total(pick(low)) <= budget_bytes:
        return pick(low)
    for _ in range(200):  # grow until the budget is met (or every tile takes its smallest candidate)
        if total(pick(high)) <= budget_bytes or high > 1e30:
            break
        high *= 4
    for _ in range(60):
        middle = math.sqrt(low * high) if low > 0 else high / 1024
        low, high = (low, middle) if total(pick(middle)) <= budget_bytes else (middle, high)
    return pick(high)


def summary(weights: list[int], choice: list[Candidate]) -> tuple[int, float]:
    """(payload bytes, point-weighted mean D_e in metres) of a choice of candidates."""
    n = sum(weights)
    return sum(c.n_bytes for c in choice), sum(w * c.d_e for w, c in zip(weights, choice)) / max(n, 1)
