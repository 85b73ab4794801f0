"""Pareto fronts per metric and the comparison of each learned row with a front of the same cloud at equal bpp.

"The full classical front" of a cloud pools every setting of every codec in the baselines registry (G-PCC octree
and trisoup, Draco, the octrees) on that cloud; each metric has its own front (D_e and D_perp lower is better,
IoU higher is better), interpolated linearly in log(bpp) and undefined (NaN) outside the measured bpp range.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mapsqueeze.benchmark.rows import Row


@dataclass(frozen=True)
class Metric:
    key: str
    label: str
    higher_is_better: bool = False


METRICS = (Metric("d_e", "D_e (m)"), Metric("d_perp", "D_perp (m)"), Metric("iou", "IoU", higher_is_better=True))
METRIC = {m.key: m for m in METRICS}


def classical_codecs() -> tuple[str, ...]:
    """Every codec of the baselines registry: together they make the full classical front."""
    from mapsqueeze.baselines import BASELINES

    return tuple(BASELINES)


def front_at(rows: list[Row], metric: Metric, bpp: float) -> float:
    """The value of the Pareto front of rows' (bpp, metric) at this bpp (NaN outside their bpp range or no rows)."""
    from mapsqueeze.baselines.rd import distortion_at

    if not rows:
        return float("nan")
    sign = -1.0 if metric.higher_is_better else 1.0
    values = [sign * getattr(r, metric.key) for r in rows]
    return float(sign * distortion_at([r.bpp for r in rows], values, bpp))


def front_indices(bpp: np.ndarray, values: np.ndarray, metric: Metric) -> np.ndarray:
    """Indices of the Pareto-optimal (bpp, value) pairs, by increasing bpp."""
    from mapsqueeze.baselines.rd import pareto_front

    return pareto_front(bpp, -values if metric.higher_is_better else values)


@dataclass
class Comparison:
    """A row and the front of its cloud at the row's bpp, per metric key (NaN: outside the front's bpp range)."""

    row: Row
    front: dict[str, float]

    def within_range(self) -> bool:
        return not np.isnan(self.front["d_e"])

    def ratio(self, key: str) -> float:
        """row / front (for D_e and D_perp: below 1 is better)."""
        return getattr(self.row, key) / self.front[key]

    def difference(self, key: str) -> float:
        """row - front (for IoU: above 0 is better)."""
        return getattr(self.row, key) - self.front[key]

    def wins(self, key: str) -> bool:
        """Strictly better than the front at equal bpp (False outside its range)."""
        value, reference = getattr(self.row, key), self.front[key]
        if np.isnan(reference):
            return False
        return value > reference if METRIC[key].higher_is_better else value < reference


def compare(rows: list[Row], front_codecs: tuple[str, ...] | None = None,
            codecs: tuple[str, ...] | None = None) -> list[Comparison]:
    """Each row of `codecs` (default: every codec outside the front) against the per-metric Pareto fronts of
    front_codecs' rows (default: the full classical front) on the same cloud at the same bpp, in row order."""
    front_codecs = classical_codecs() if front_codecs is None else front_codecs
    fronts: dict[str, list[Row]] = {}
    for r in rows:
        if r.codec in front_codecs:
            fronts.setdefault(r.cloud, []).append(r)
    out = []
    for r in rows:
        if r.codec in front_codecs or (codecs is not None and r.codec not in codecs):
            continue
        front = fronts.get(r.cloud, [])
        out.append(Comparison(r, {m.key: front_at(front, m, r.bpp) for m in METRICS}))
    return out
