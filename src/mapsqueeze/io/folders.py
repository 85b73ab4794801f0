"""The point-cloud files of a folder, recognised by the extensions of the format table (`formats.format_name`)."""

import os
from pathlib import Path

from mapsqueeze.errors import PointCloudFormatError
from mapsqueeze.io.formats import format_name


def is_point_cloud_path(path: str | os.PathLike) -> bool:
    """True when the path's extension names a supported point-cloud format (the file is not opened)."""
    try:
        format_name(path)
    except PointCloudFormatError:
        return False
    return True


def point_cloud_files(folder: str | os.PathLike) -> list[Path]:
    """The files directly in `folder` whose extension names a supported format, sorted by path; hidden files (a
    name starting with ".", such as a dataset write's temporary files) are left out."""
    return sorted(path for path in Path(folder).iterdir()
                  if path.is_file() and not path.name.startswith(".") and is_point_cloud_path(path))
