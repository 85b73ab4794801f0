"""LAS/LAZ (laspy; LAZ through lazrs): every standard point field, extra-bytes dimensions and header metadata.

Attributes read: the point format's standard fields `intensity`, `return_number`, `number_of_returns`,
`classification`, `scan_angle_rank` (formats 0-5) or `scan_angle` (6-10), `user_data`, `point_source_id`, and where
the format has them `gps_time`, `red`, `green`, `blue`, `nir`; its bit fields `scan_direction_flag`,
`edge_of_flight_line`, `synthetic`, `key_point`, `withheld`, and in formats 6-10 `overlap` and `scanner_channel`
(uint8 each); then every extra-bytes dimension (scaled when it declares scales; a k-element array as the columns
`name_0` .. `name_{k-1}`, written back as the array). Metadata (`PointCloud.metadata["las"]`): version, point
format, scales, offsets, system identifier, the VLRs and EVLRs other than extra-bytes and LAZ records
(GeoKeyDirectory, GeoAscii/Double params, WKT: the CRS) as base64, the WKT flag, and the extra dimensions'
descriptions, types, scales, offsets and no-data values; `metadata["crs"]` is a readable summary (`EPSG:32632` from
the GeoKeyDirectory, or the WKT). A `metadata["crs"]` without CRS records (given through the API) is written as a
WKT record where it is a WKT, and not at all otherwise.

Writing: the point format is the metadata's when it has every standard field given and they hold the values (whole
numbers within each field's range), else the first of 0, 1, 2, 3, 6, 7, 8 that does (classification 40: format 6). A
standard field that no such format holds (a float intensity of 0.37) is written exactly as the extra dimension
`name_dtype` (intensity_float32), with a FieldRenamedWarning. EVLRs are written after the points, and a file with
EVLRs is LAS 1.4. Scale and offset are the metadata's when the cloud fits them, else the minimum rounded down to
whole metres and per axis LAS_SCALE_M (error at most 0.05 mm) where its extent is below 2^31 * 0.1 mm (about 214
km), else 1 mm or 1 cm (21,000 km: any cloud within the 10,000 km of the origin that validation allows). Other
attributes become extra-bytes dimensions of their own dtype.

Colour: LAS colour (`red`, `green`, `blue`, `nir`) is 16-bit (0..65535, ASPRS), and an attribute's dtype is its bit
depth, so uint8 channels (PLY uchar, PCD packed rgb) are written scaled by EIGHT_BIT_SCALE (255 -> 65535) and
channels of any other dtype as they are. Read colour stays 16-bit whatever the writer after it: PLY and PCD store it
as uint16 (PLY ushort, PCD fields `red` `green` `blue` of TYPE U SIZE 2), so LAS -> PLY -> LAS keeps it exactly.
"""

import base64
import re
import warnings
from collections.abc import Iterator
from pathlib import Path

import laspy
import lazrs
from laspy.vlrs.known import ExtraBytesVlr
from laspy.vlrs.vlrlist import VLRList
import numpy as np

from mapsqueeze.errors import FieldRenamedWarning, InvalidPointCloudError, PointCloudFormatError
from mapsqueeze.io.atomic import atomic_output
from mapsqueeze.io.pointcloud import ChunkSource, CloudStats, PointCloud, split_columns, validate_points

LAS_SCALE_M = 1e-4
"""LAS/LAZ coordinate resolution in metres (quantisation error at most half of it) of an axis that spans less than
2^31 of it (about 214 km)."""
_COARSER_SCALES = (LAS_SCALE_M, 1e-3, 1e-2)
"""The resolutions (metres) tried in turn for an axis, the first under which its extent fits LAS's 32-bit integers."""

STANDARD_FIELDS = ("intensity", "return_number", "number_of_returns", "classification", "scan_angle_rank",
                   "scan_angle", "user_data", "point_source_id", "gps_time", "red", "green", "blue", "nir",
                   "scan_direction_flag", "edge_of_flight_line", "synthetic", "key_point", "withheld", "overlap",
                   "scanner_channel")
"""Standard LAS point fields read and written as attributes (those the point format has)."""
COLOUR_FIELDS = ("red", "green", "blue", "nir")
"""The standard fields holding 16-bit colour."""
EIGHT_BIT_SCALE = 257
"""Factor from 8-bit to 16-bit colour (v * 257 maps 0..255 onto 0..65535; v >> 8 undoes it)."""

_WRITE_FORMATS = (0, 1, 2, 3, 6, 7, 8)
_INTEGER_LIMIT = 2**31 - 1
_MANAGED_RECORDS = {("LASF_Spec", 4), ("laszip encoded", 22204), ("LASF_Spec", 7)}  # laspy writes these itself
_PROJECTED_CRS_KEY, _GEOGRAPHIC_CRS_KEY = 3072, 2048
_CRS_RECORDS = {("LASF_Projection", 34735), ("LASF_Projection", 2112)}  # GeoKeyDirectory, WKT
_WKT = re.compile(r"\s*[A-Za-z_]+\s*\[")
_ERRORS = (laspy.errors.LaspyException, lazrs.LazrsError, ValueError, EOFError)


def _vlr_record(vlr) -> dict:
    return {"user_id": vlr.user_id, "record_id": int(vlr.record_id), "description": vlr.description,
            "data": base64.b64encode(vlr.record_data_bytes()).decode("ascii")}


def _crs_summary(records: list) -> str | None:
    """`EPSG:code` from a GeoKeyDirectory, else the WKT text, else None."""
    for vlr in records:
        if isinstance(vlr, laspy.vlrs.known.GeoKeyDirectoryVlr):
            for key in vlr.geo_keys:
                if key.id in (_PROJECTED_CRS_KEY, _GEOGRAPHIC_CRS_KEY) and key.tiff_tag_location == 0:
                    return f"EPSG:{key.value_offset}"
    for vlr in records:
        if isinstance(vlr, laspy.vlrs.known.WktCoordinateSystemVlr):
            return vlr.string.strip("\0 ")
    return None


def _holds_crs_records(las: dict) -> bool:
    """Whether the LAS records of `metadata["las"]` include a CRS (GeoKeyDirectory or WKT)."""
    return any((r["user_id"], r["record_id"]) in _CRS_RECORDS for r in las.get("vlrs", []) + las.get("evlrs", []))


def _given_wkt(metadata: dict) -> str | None:
    """metadata["crs"] where it is a WKT string and the LAS records hold no CRS (e.g. a CRS given through the API):
    the WKT to write as a record."""
    crs = metadata.get("crs")
    if isinstance(crs, str) and _WKT.match(crs) and not _holds_crs_records(metadata.get("las", {})):
        return crs
    return None


def keeps_crs(metadata: dict) -> bool:
    """Whether write_las keeps metadata["crs"]: as the LAS records it was read from, or as a WKT record. An EPSG code
    alone ("EPSG:32632") is not written: LAS needs the CRS's WKT or GeoTIFF keys, which the code alone does not
    give without a projection database."""
    return ("crs" not in metadata or _holds_crs_records(metadata.get("las", {}))
            or _given_wkt(metadata) is not None)


def _metadata(header: laspy.LasHeader, evlrs: list) -> dict:
    vlrs = [vlr for vlr in header.vlrs if (vlr.user_id, vlr.record_id) not in _MANAGED_RECORDS]
    evlrs = [vlr for vlr in evlrs if (vlr.user_id, vlr.record_id) not in _MANAGED_RECORDS]
    extra = {}
    no_data = {struct.format_name(): struct.no_data for vlr in header.vlrs if isinstance(vlr, ExtraBytesVlr)
               for struct in vlr.extra_bytes_structs if struct.no_data is not None}  # laspy's dimensions drop it
    for info in header.point_format.extra_dimensions:
        entry = {"description": info.description.strip("\0 "), "type": np.dtype(info.dtype).base.str}
        if info.num_elements > 1:
            entry["count"] = int(info.num_elements)
        if info.name in no_data:
            entry["no_data"] = no_data[info.name].tolist()
        if info.scales is not None:
            entry.update(scales=[float(v) for v in np.atleast_1d(info.scales)],
                         offsets=[float(v) for v in np.atleast_1d(info.offsets)])
        extra[info.name] = entry
    las = {"version": str(header.version), "point_format": int(header.point_format.id),
           "scales": [float(v) for v in header.scales], "offsets": [float(v) for v in header.offsets],
           "system_identifier": header.system_identifier.strip("\0 "),
           "wkt": bool(header.global_encoding.wkt),
           "vlrs": [_vlr_record(vlr) for vlr in vlrs], "evlrs": [_vlr_record(vlr) for vlr in evlrs],
           "extra_bytes": extra}
    metadata = {"las": las}
    crs = _crs_summary(vlrs + evlrs)
    if crs:
        metadata["crs"] = crs
    return metadata


def _attributes(record, point_format: laspy.PointFormat) -> dict[str, np.ndarray]:
    names = set(point_format.dimension_names)
    attributes = {name: np.array(record[name]) for name in STANDARD_FIELDS if name in names}
    for name in point_format.extra_dimension_names:
        attributes.update(split_columns(name, np.array(record[name])))
    return attributes


def las_chunks(path: Path, chunk_points: int, attributes: bool = True) -> Iterator[PointCloud]:
    try:
        with laspy.open(path) as reader:
            declared, seen = reader.header.point_count, 0
            if declared == 0:
                raise InvalidPointCloudError(f"{path}: the point cloud is empty")
            _check_point_data_size(path, reader.header)
            metadata = _metadata(reader.header, list(reader.header.evlrs or []))
            for part in reader.chunk_iterator(chunk_points):
                if len(part):
                    points = validate_points(np.column_stack([np.asarray(part.x), np.asarray(part.y),
                                                              np.asarray(part.z)]), str(path), seen, declared)
                    _check_within_bounds(path, reader.header, points, seen)
                    _check_gps_time(path, part, seen)
                    yield (PointCloud(points, _attributes(part, reader.header.point_format), metadata)
                           if attributes else PointCloud(points))
                seen += len(part)
            if seen != declared:
                raise PointCloudFormatError(
                    f"{path}: LAS header declares {declared:,} points, the file holds {seen:,}")
    except lazrs.LazrsError as exc:
        raise PointCloudFormatError(f"{path}: corrupt or truncated LAZ point data ({exc})") from None
    except _ERRORS as exc:
        raise PointCloudFormatError(f"{path}: corrupt LAS/LAZ file ({exc})") from None


def _check_point_data_size(path: Path, header: laspy.LasHeader) -> None:
    """PointCloudFormatError when an uncompressed LAS file ends before the point records its header declares, or
    holds more whole records between the header and what follows the points (EVLRs, waveform data, the end of the
    file) than it declares: a wrong count, by which points would be left out unsaid."""
    if header.are_points_compressed:
        return
    record, start = header.point_format.size, header.offset_to_point_data
    needed = start + header.point_count * record
    size = path.stat().st_size
    if size < needed:
        raise PointCloudFormatError(
            f"{path}: LAS header declares {header.point_count:,} points of {record} bytes from byte {start:,}, "
            f"{needed:,} bytes in all; the file holds {size:,} (truncated?)")
    follows = [offset for offset in (header.start_of_first_evlr, header.start_of_waveform_data_packet_record)
               if offset and offset >= needed]
    held = (min(follows + [size]) - start) // record
    if held > header.point_count:
        raise PointCloudFormatError(
            f"{path}: LAS header declares {header.point_count:,} points, the file holds {held:,} point records "
            "(a wrong point count in the header)")


def _check_gps_time(path: Path, part, first: int) -> None:
    """PointCloudFormatError at a GPS time of NaN or infinity: corrupt point data (LAZ decodes damaged bytes into
    values without an error, and no LAS writer stores such a time)."""
    if "gps_time" not in part.point_format.dimension_names:
        return
    bad = ~np.isfinite(np.asarray(part.gps_time))
    if bad.any():
        raise PointCloudFormatError(f"{path}: point {first + int(np.argmax(bad)):,} has a GPS time of "
                                    f"{np.asarray(part.gps_time)[np.argmax(bad)]}: corrupt point data")


def _check_within_bounds(path: Path, header: laspy.LasHeader, points: np.ndarray, first: int) -> None:
    """PointCloudFormatError when a point lies outside the header's bounding box by more than a coordinate step:
    corrupt point data (LAZ decodes damaged bytes into points without an error) or a header with wrong bounds. A
    header whose bounds are all zero (left unset by its writer) is not checked."""
    if not (np.any(header.mins) or np.any(header.maxs)):
        return
    slack = np.asarray(header.scales) + 1e-9 * np.abs(np.asarray(header.maxs))
    outside = ((points < np.asarray(header.mins) - slack) | (points > np.asarray(header.maxs) + slack)).any(axis=1)
    if outside.any():
        index = int(np.argmax(outside))
        x, y, z = points[index]
        raise PointCloudFormatError(
            f"{path}: point {first + index:,} ({x:.3f}, {y:.3f}, {z:.3f}) lies outside the header's bounds "
            f"({', '.join(f'{v:.3f}' for v in header.mins)} to {', '.join(f'{v:.3f}' for v in header.maxs)}): "
            "corrupt point data, or a header with wrong bounds (`lasinfo -repair_bb` or `pdal translate` rewrites "
            "them)")


def _misfits(stats: CloudStats, point_format: laspy.PointFormat) -> list[str]:
    """The standard integer fields of `point_format` whose attribute values are not whole numbers within the field's
    range (classification 40 in formats 0-5, a float intensity of 0.37)."""
    misfits = []
    for name in point_format.dimension_names:
        if name not in stats.dtypes or name not in stats.ranges:
            continue
        limits = _integer_limits(point_format, name)
        low, high, whole = stats.ranges[name]
        if name in COLOUR_FIELDS and stats.dtypes[name] == np.uint8:
            low, high = low * EIGHT_BIT_SCALE, high * EIGHT_BIT_SCALE
        if limits is not None and not (whole and limits[0] <= low and high <= limits[1]):
            misfits.append(name)
    return misfits


def _point_format(stats: CloudStats, preferred: int | None) -> laspy.PointFormat:
    """The preferred point format, else the first of _WRITE_FORMATS, that has every standard field given, and of
    those the first whose fields hold the values given; if none does, the first with the fewest fields that do
    not (a float intensity and classification 44: format 6, where only the intensity cannot stay)."""
    wanted = {name for name in stats.dtypes if name in STANDARD_FIELDS}
    candidates = [laspy.PointFormat(candidate)
                  for candidate in ([preferred] if preferred is not None else []) + list(_WRITE_FORMATS)
                  if wanted <= set(laspy.PointFormat(candidate).dimension_names)]
    if not candidates:
        raise InvalidPointCloudError(f"no LAS point format holds all of {', '.join(sorted(wanted))}")
    return min(candidates, key=lambda candidate: len(_misfits(stats, candidate)))  # the first of the fewest


def _extra_name(name: str, dtype: np.dtype, taken) -> str:
    """The extra dimension that holds standard field `name`'s values where the field cannot: `name_dtype`, e.g.
    intensity_float32 (at most 32 characters, LAS's limit)."""
    suffix = f"_{np.dtype(dtype).name}"
    extra = name[:32 - len(suffix)] + suffix
    if extra.lower() in {other.lower() for other in taken}:
        raise InvalidPointCloudError(f"attribute {name!r} does not fit LAS's {name} field and {extra!r}, the extra "
                                     "dimension that would hold it, is taken; rename one of them")
    return extra


def _fits(scales: np.ndarray, offsets: np.ndarray, stats: CloudStats) -> bool:
    if not (scales > 0).all():
        return False
    low, high = (stats.lowest - offsets) / scales, (stats.highest - offsets) / scales
    return bool((np.abs(low) < _INTEGER_LIMIT).all() and (np.abs(high) < _INTEGER_LIMIT).all())


def _header(stats: CloudStats) -> tuple[laspy.LasHeader, VLRList, dict[str, str | tuple[str, int]]]:
    """The header to write, the EVLRs to write after the points (the streaming writer leaves header.evlrs out) and
    where each attribute is written: a dimension's name, or (name, index) of an array dimension's element (the
    columns name_0 .. name_{k-1} of an array read from LAS). A file with EVLRs is LAS 1.4, the first version with
    EVLRs."""
    las = stats.metadata.get("las", {})
    point_format = _point_format(stats, las.get("point_format")).id
    version = las.get("version", "1.4") if point_format < 6 and not las.get("evlrs") else "1.4"
    header = laspy.LasHeader(version=version if version in ("1.2", "1.3", "1.4") else "1.4",
                             point_format=point_format)
    scales, offsets = np.asarray(las.get("scales", [0.0] * 3)), np.asarray(las.get("offsets", [0.0] * 3))
    if not _fits(scales, offsets, stats):
        offsets = np.floor(stats.lowest)
        extent = stats.highest - offsets
        scales = np.array([next((scale for scale in _COARSER_SCALES if span / scale < _INTEGER_LIMIT), np.nan)
                           for span in extent])
        if np.isnan(scales).any():
            raise InvalidPointCloudError(
                f"the cloud spans {extent.max() / 1e3:.0f} km, more than LAS can hold at {_COARSER_SCALES[-1] * 1e3:g} "
                f"mm resolution (about {_INTEGER_LIMIT * _COARSER_SCALES[-1] / 1e3:.0f} km)")
    header.offsets, header.scales = offsets, scales
    if las.get("system_identifier"):
        header.system_identifier = las["system_identifier"]
    header.vlrs.extend(laspy.VLR(r["user_id"], r["record_id"], r["description"], base64.b64decode(r["data"]))
                       for r in las.get("vlrs", []))
    evlrs = VLRList(laspy.VLR(r["user_id"], r["record_id"], r["description"], base64.b64decode(r["data"]))
                          for r in las.get("evlrs", []))
    wkt = _given_wkt(stats.metadata)
    if wkt:
        header.vlrs.append(laspy.vlrs.known.WktCoordinateSystemVlr(wkt))
    if (las.get("wkt") or wkt) and header.version.minor >= 4:
        header.global_encoding.wkt = True
    standard = set(header.point_format.dimension_names)
    described = las.get("extra_bytes", {})
    params, stored = [], {}
    misfits = set(_misfits(stats, header.point_format))
    for array, info in described.items():  # name_0 .. name_{k-1} read from a k-element array dimension
        columns = [f"{array}_{index}" for index in range(info.get("count", 1))]
        if len(columns) > 1 and array not in stats.dtypes and all(column in stats.dtypes for column in columns) \
                and len({stats.dtypes[column] for column in columns}) == 1:
            stored.update({column: (array, index) for index, column in enumerate(columns)})
    for name, dtype in stats.dtypes.items():
        if name in stored:
            array, index = stored[name]
            info, count = described[array], described[array]["count"]
            if index == 0 and "scales" in info and dtype.kind == "f":
                params.append(laspy.ExtraBytesParams(array, np.dtype((np.dtype(info["type"]), count)),
                                                     info["description"], offsets=info["offsets"],
                                                     scales=info["scales"], no_data=_no_data(info, dtype)))
            elif index == 0:
                params.append(laspy.ExtraBytesParams(array, np.dtype((dtype, count)), info["description"],
                                                     no_data=_no_data(info, dtype)))
            continue
        if name in misfits:
            stored[name] = _extra_name(name, dtype, set(standard) | set(stats.dtypes))
            params.append(laspy.ExtraBytesParams(stored[name], dtype, f"{name} values"))
            continue
        stored[name] = name
        if name in standard:
            continue
        if name.lower() in {dim.lower() for dim in standard}:
            raise InvalidPointCloudError(f"attribute {name!r} clashes with a standard LAS field; rename it")
        info = described.get(name, {})
        if "scales" in info and dtype.kind == "f":
            params.append(laspy.ExtraBytesParams(name, info["type"], info["description"], offsets=info["offsets"],
                                                 scales=info["scales"], no_data=_no_data(info, dtype)))
        else:
            params.append(laspy.ExtraBytesParams(name, dtype, info.get("description", ""),
                                                 no_data=_no_data(info, dtype)))
    header.add_extra_dims(params)
    return header, evlrs, stored


def _no_data(info: dict, dtype: np.dtype) -> list | None:
    """The no-data values of an extra dimension as read (`metadata["las"]["extra_bytes"][name]["no_data"]`), where
    the attribute still has the type they were read for (a dimension stored as the raw integers: the same kind)."""
    values = info.get("no_data")
    if values is None or np.dtype(info["type"]).kind != np.dtype(dtype).kind and "scales" not in info:
        return None
    return values


def write_las(path: Path, chunks: ChunkSource, stats: CloudStats, compress: bool) -> tuple[str, ...]:
    header, evlrs, stored = _header(stats)
    standard = set(header.point_format.dimension_names)
    try:
        with atomic_output(path) as temp, open(temp, "wb") as stream, \
                laspy.open(stream, mode="w", header=header, do_compress=compress, closefd=False,
                           laz_backend=laspy.LazBackend.Lazrs if compress else None) as writer:
            for chunk in chunks():
                record = laspy.ScaleAwarePointRecord.zeros(len(chunk), header=header)
                record.x, record.y, record.z = chunk.points[:, 0], chunk.points[:, 1], chunk.points[:, 2]
                elements: dict[str, dict[int, np.ndarray]] = {}
                for name, values in chunk.attributes.items():
                    name = stored[name]
                    if isinstance(name, tuple):
                        elements.setdefault(name[0], {})[name[1]] = values
                        continue
                    if name in COLOUR_FIELDS and values.dtype == np.uint8:
                        values = values * np.uint16(EIGHT_BIT_SCALE)
                    limits = _integer_limits(record.point_format, name) if name in standard else None
                    if limits is not None:
                        low, high = limits
                        if values.min() < low or values.max() > high or not np.array_equal(values, np.round(values)):
                            raise InvalidPointCloudError(
                                f"LAS {name} is an integer in {low}..{high} and attribute {name!r} is not; "
                                "rename it to store it as an extra dimension")
                        record[name] = values.astype(np.int64)
                    else:
                        record[name] = values
                for array, columns in elements.items():
                    record[array] = np.column_stack([columns[index] for index in range(len(columns))])
                writer.write_points(record)
            if evlrs:
                writer.write_evlrs(evlrs)
    except (laspy.errors.LaspyException, OverflowError) as exc:
        raise InvalidPointCloudError(f"cannot write LAS ({exc})") from None
    for name, extra in stored.items():
        if extra != name and not isinstance(extra, tuple):
            low, high = _integer_limits(header.point_format, name)
            warnings.warn(FieldRenamedWarning(
                f"{path.name}: LAS {name} is an integer in {low}..{high} (point format {header.point_format.id}) "
                f"and attribute {name!r} ({stats.dtypes[name].name}) is not; written as the extra dimension "
                f"{extra!r}"), stacklevel=2)
    return tuple(dict.fromkeys(extra[0] if isinstance(extra, tuple) else extra for extra in stored.values()))


def _integer_limits(point_format: laspy.PointFormat, name: str) -> tuple[int, int] | None:
    """Smallest and largest value of a standard integer field (bit fields by their width); None if scaled/float."""
    dimension = point_format.dimension_by_name(name)
    if dimension.is_scaled or (dimension.dtype is not None and np.dtype(dimension.dtype).kind == "f"):
        return None
    return int(dimension.min), int(dimension.max)
