"""Typed exceptions. The CLI turns any MapsqueezeError into one error line and a non-zero exit."""


class MapsqueezeError(Exception):
    """Base class of every error mapsqueeze raises on bad input or bad state."""


class PointCloudFormatError(MapsqueezeError):
    """A point-cloud file is missing, unreadable, corrupt or of an unknown format."""


class InvalidPointCloudError(MapsqueezeError):
    """A point cloud is empty, has NaN/inf values, the wrong shape or absurd coordinates."""


class OutputError(MapsqueezeError):
    """An output file cannot be written: its folder is missing or read-only, a directory, device or pipe has its
    name, or it is the command's input."""


class ContainerError(MapsqueezeError):
    """A .msq container is truncated, corrupt or of an unsupported version."""


class ModelError(MapsqueezeError):
    """A model or checkpoint cannot be found, loaded or matched to its configuration."""


class DataError(MapsqueezeError):
    """Scans, poses, calibration, labels or a dataset manifest are missing, incomplete or inconsistent."""


class SimulationError(MapsqueezeError):
    """A simulator request is invalid: unknown sensor or preset, impossible sizes or counts."""


class BaselineError(MapsqueezeError):
    """A baseline codec is unavailable, was given a bad setting, or its external tool failed."""


class DecodeLimitError(MapsqueezeError):
    """A container asks for more decoded points than the decoder's limit allows (a guard against crafted files)."""


class MapsqueezeWarning(UserWarning):
    """Base class of the warnings mapsqueeze gives: the command line prints each as one `warning: ...` line."""


class FieldRenamedWarning(MapsqueezeWarning):
    """An attribute was written under another name than its own, where the output format's field of that name
    cannot hold its values (a float intensity in LAS: written as the extra dimension intensity_float32)."""


class TileLimitWarning(MapsqueezeWarning):
    """A file was written whose tiles decode to more points than decompress allows by default (--max-tile-points)."""


class CrsNotWrittenWarning(MapsqueezeWarning):
    """A point-cloud file was written without the CRS its metadata holds: the format has no place for it (all but
    LAS/LAZ), or LAS cannot take it as given (an EPSG code without its WKT)."""
