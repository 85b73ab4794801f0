"""The interface every classical baseline codec implements (its failures raise errors.BaselineError)."""

from abc import ABC, abstractmethod
from typing import ClassVar

import numpy as np

from mapsqueeze.errors import BaselineError

Setting = dict[str, float | int | str]
"""One quality level of a codec: plain JSON-able values (e.g. {"voxel_m": 0.4, "bits": 10})."""


class BaselineCodec(ABC):
    """A classical point-cloud codec swept over quality levels for the rate-distortion benchmark.

    Points are (N, 3) float64 metres in a local frame; `encode` is deterministic (same input, same bytes) and
    its bytes are all a decoder needs, so len(encode(...)) is the rate.
    """

    name: ClassVar[str]
    requirement: ClassVar[str] = ""
    """What `available()` needs, for the message shown when the codec is skipped."""

    def available(self) -> bool:
        """Whether the codec can run on this machine."""
        return True

    @abstractmethod
    def settings(self) -> list[Setting]:
        """The quality levels of the benchmark sweep."""

    @abstractmethod
    def encode(self, points: np.ndarray, setting: Setting) -> bytes:
        """Compress (N, 3) points (metres) at one quality level."""

    @abstractmethod
    def decode(self, data: bytes) -> np.ndarray:
        """Decompress to (K, 3) float64 points (metres); K may differ from N."""


def setting_label(setting: Setting) -> str:
    """A short stable text for a setting, e.g. 'voxel_m=0.4,bits=10' (for tables and CSV)."""
    return ",".join(f"{key}={value}" for key, value in setting.items())


def setting_value(setting: Setting, key: str, codec: str) -> float | int | str:
    """`setting[key]`, or BaselineError naming the codec when the key is missing."""
    try:
        return setting[key]
    except (KeyError, TypeError):
        raise BaselineError(f"{codec}: setting {setting!r} lacks {key!r}") from None


def setting_number(setting: Setting, key: str, codec: str, low: float, high: float = float("inf")) -> float:
    """`setting[key]` as a float in [low, high], or BaselineError."""
    value = setting_value(setting, key, codec)
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise BaselineError(f"{codec}: {key} must be a number, got {value!r}")
    if not low <= float(value) <= high:
        raise BaselineError(f"{codec}: {key}={value!r} is outside [{low}, {high}]")
    return float(value)
