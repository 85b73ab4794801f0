"""One benchmark result (a codec at one setting on one cloud) and the results.csv that holds them."""

from __future__ import annotations

import csv
from dataclasses import asdict, dataclass, fields
from pathlib import Path

from mapsqueeze.errors import MapsqueezeError


@dataclass
class Row:
    cloud: str
    codec: str
    setting: str
    weights: str
    """SHA-256 of the learned model's weights ("" for a classical codec): a resumed run reruns rows whose model
    weights changed."""
    n_points: int
    n_bytes: int
    bpp: float
    d_e: float
    """Symmetric mean point-to-point distance (metres)."""
    d_perp: float
    """Symmetric mean point-to-plane distance (metres)."""
    iou: float
    n_decoded: int
    encode_s: float
    decode_s: float

    def key(self) -> tuple[str, str, str]:
        """What a row measures: (cloud, codec, setting)."""
        return self.cloud, self.codec, self.setting


def read_rows(path: Path) -> list[Row]:
    """Rows of an earlier results.csv (none when absent); MapsqueezeError for a CSV of another layout."""
    if not path.is_file():
        return []
    casts = {"str": str, "int": int, "float": float}
    types = {field.name: casts[field.type] for field in fields(Row)}
    with open(path, newline="") as f:
        reader = csv.DictReader(f)
        if reader.fieldnames != list(types):
            raise MapsqueezeError(f"{path}: not a results.csv of this version (columns {reader.fieldnames}); "
                                  "use --fresh")
        try:
            return [Row(**{k: types[k](v) for k, v in record.items()}) for record in reader]
        except (KeyError, TypeError, ValueError) as exc:
            raise MapsqueezeError(f"{path}: not a results.csv of this version ({exc}); use --fresh") from None


def write_rows(rows: list[Row], path: Path) -> None:
    """All rows -> CSV at path (atomically)."""
    from mapsqueeze.io import atomic_output

    with atomic_output(path) as tmp, open(tmp, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=[field.name for field in fields(Row)])
        writer.writeheader()
        writer.writerows(asdict(r) for r in rows)
