"""Encoder-signalled decode post-filter of network tiles (like a video codec's adaptive loop filter).

The decoder's native output gathers in clumps around the embedding points, spread a few centimetres across the
surfaces, with stray points between them: it leaves occupied space empty and fills empty space (the paper's IoU).
The post-filter reworks a decoded tile with local surface operations (`geometry.surface`). Two kinds:

- patch planes (bit 5, the default of `compress`): each decoder patch (the points one parent of the last
  PATCH_LEVELS upsampling levels spawned, consecutive in the decoder's output) pulled PATCH_STRENGTH of the way onto
  its PCA plane, plus 1 or 2 extra points per point on disks of PATCH_RADIUS_M in it; no neighbour search, about
  10-20 ms per 250k decoded points in the encoder's compiled kernel, 25-40 ms in the decoder's numpy (the same
  bytes, `apply_patch_filter`). The encoder tries the PATCH_CANDIDATES and keeps the one with the highest IoU
  where it beats the paper's decode (`choose_patch_filter`: their points marked on one occupancy grid as they are
  made, about 20 ms per 250k decoded points for both).
- patch choices (bit 7, chosen by `compress` over patch planes where they pay): the same patch operation with one
  of PATCH_OPTIONS per patch (pull strength, extra points, disk radius), the choices entropy coded at the start of
  the tile's payload (`encode_patch_choices`). The encoder decodes the tile as the decoder will and searches the
  options patch by patch for the highest IoU with the tile's points (`search_patch_choices`; for e3 also
  weighing D_e and the choices' bits, its config's `patch_choice_copy_weight`).
- neighbour planes (bits 0-4, `--post-filter auto`): snap: each point projected onto the PCA plane of its k nearest
  decoded points; spread: extra points on small disks of those planes around each point (fills the gaps between
  clumps); isolated: points with fewer than ISOLATED_MIN_NEIGHBOURS others within ISOLATED_RADIUS_M dropped. The
  encoder tries the settings of CANDIDATES and stores the one that gives the highest IoU without raising D_e by
  more than MAX_D_E_INCREASE (`choose_post_filter`); seconds per tile.

One byte per tile (the tile table's post-filter field, docs/format.md); the decoder applies it. Setting 0 is the
paper's decode. The byte: bits 0-1 snap (0 off, else SNAP_NEIGHBOURS[bits] nearest points), bits 2-3 spread
(SPREAD[bits]: extra points per point and disk radius in metres), bit 4 isolated-point removal; or bit 5 patch
planes (bits 0-4 zero) with bit 6: two extra points per point instead of one; or bit 7 alone: patch choices;
bit 7 zero otherwise, bit 6 zero without bit 5.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mapsqueeze.codec.entropy import ByteReader, ByteWriter, Histogram, SymbolReader, SymbolWriter
from mapsqueeze.errors import ContainerError
from mapsqueeze.geometry.surface import disk_samples, keep_supported, local_planes, project_to_planes
from mapsqueeze.metrics import IOU_VOXEL_M, d_euclidean, iou, nearest_tree

OFF = 0
"""The setting that leaves the decoded tile as the network gives it (the paper's decode; files before version 3)."""

SNAP_NEIGHBOURS = (0, 16, 32, 48)
"""Neighbourhood size of the snapping planes per value of bits 0-1 (0: no snapping)."""

SPREAD = ((0, 0.0), (1, 0.05), (1, 0.10), (2, 0.10))
"""(extra points per decoded point, disk radius in metres) per value of bits 2-3."""

ISOLATED_RADIUS_M = 0.2
ISOLATED_MIN_NEIGHBOURS = 4
"""Bit 4 drops the points with fewer than this many other decoded points within ISOLATED_RADIUS_M."""

_ISOLATED_BIT = 1 << 4
PATCH = 1 << 5
"""Bit 5: patch planes (`patch_planes_byte`)."""
_PATCH_TWO_COPIES_BIT = 1 << 6
_NEIGHBOUR_BITS = 0b11111
PATCH_VERSION = 5
"""First container version whose tiles may carry patch planes."""

PATCH_CHOICES = 1 << 7
"""Bit 7 alone: patch choices (`apply_patch_choices`); the tile's payload starts with the choice stream."""
PATCH_CHOICE_VERSION = 6
"""First container version whose tiles may carry patch choices."""

PATCH_LEVELS = 4
"""A patch is the points one parent of the decoder's last 4 upsampling levels spawned: all the points of one
embedding point for the shipped models (625 for e1's 5 x 5 x 5 x 5, 1296 for e0, 256 for e2 and e3). On the real
KITTI and Ouster submaps with e0..e3, 4 levels gave a mean IoU gain of +0.014 / +0.016 (1 / 2 extra points) against
+0.012 / +0.013 with 3 levels (125 points for e1), at D_e changes of -4 to +6 % against -3 to +3 %."""
PATCH_COPIES = (1, 2)
"""Extra points per point on the patch plane with bit 6 clear or set (fills the gaps between clumps)."""
PATCH_STRENGTH = 0.7
"""Fraction of each point's offset from its patch's plane removed (1: projection onto it). Of 0.7 and 1, 0.7 gave
more IoU on the real KITTI and Ouster submaps (1 also empties voxels the decode rightly occupies), at lower D_e."""
PATCH_RADIUS_M = 0.05
"""Radius in metres of the extra points' disk around each point in its patch plane (5 cm gave more IoU than 10)."""


PATCH_OPTIONS = ((0.0, 0, 0.05), (0.7, 0, 0.05), (1.0, 0, 0.05), (0.0, 1, 0.05), (0.7, 1, 0.05), (1.0, 1, 0.05),
                 (0.0, 2, 0.05), (0.7, 2, 0.05), (1.0, 2, 0.05), (0.7, 2, 0.10), (1.0, 2, 0.10))
"""(pull strength, extra points per point, disk radius in metres) of each patch choice, indexed by the coded
symbol; option 0 leaves the patch as the network gives it. On the real KITTI and Ouster submaps with e0..e3 each
option is chosen for 2-28 % of the patches. Dropping a patch as a twelfth option raised IoU by another 0.015-0.039
(e1, e3) but D_e by 8-50 %; four further options (more copies, wider disks) raised it by 0.006-0.009 for 11-21 %
more decoded points (BENCHMARKS.md, "Patch choices")."""
PATCH_CHOICE_SWEEPS = 3
"""Greedy sweeps over a tile's patches (`geometry.occupancy.patch_option_ious`): on the real KITTI and Ouster
submaps with e0..e3, 1 / 2 / 3 sweeps reach all but 0.0017 / 0.0002 / 0.0001 of the IoU of 8; a fourth changed at
most 2 of 193-1407 patches."""
IOU_PER_LOG_RATE = 0.12
"""IoU the full classical front gains per e-fold of rate on the real KITTI and Ouster submaps: 0.10-0.13 between
their shipped rate points from 0.08 to 1 bpp, except 0.01 between KITTI's e2 and e3 (BENCHMARKS.md, "Against G-PCC
and the full classical front: the default decode"). Patch choices are kept when they gain more IoU than this
times the log of the payload growth they cost, so they beat moving along the front."""
PATCH_CHOICE_RATE_SWEEPS = 2
"""Sweeps charging the choices' bits after the PATCH_CHOICE_SWEEPS without, for a model with a copy weight
(`ModelConfig.patch_choice_copy_weight`)."""


def patch_planes_byte(copies: int) -> int:
    """The post-filter byte of patch planes with `copies` extra points per point (one of PATCH_COPIES)."""
    return PATCH | (_PATCH_TWO_COPIES_BIT if copies == PATCH_COPIES[1] else 0)


PATCH_CANDIDATES = tuple(patch_planes_byte(copies) for copies in PATCH_COPIES)
"""The patch-plane settings the encoder tries, in order of decoded points (the second extra point per point decodes
3 instead of 2 times the native count)."""
CHOICE_SEARCH_START = PATCH_CANDIDATES[0]
"""The patch-plane setting from whose option the encoder searches a tile's patch choices before it knows the tile's
own setting (`codec.tilejobs`): one extra point per point, the setting that every tile of the real submaps and of
the benchmarks' 25-tile map takes with each shipped model."""
CLEAR_PAY_FRACTION = 0.5
"""Patch choices pay clearly when they would pay for a network payload of this fraction of its bytes
(`choices_pay_clearly`): the file's final coding of the payload moves its size by a few percent at most, so such
choices are kept (`patch_choice_prefix`) and the tile's own patch-plane setting, their fallback, is not needed."""
PATCH_EXTRA_COPY_MIN_IOU_GAIN = 0.01
"""IoU two extra points per point must gain over one to be chosen: the second copy adds the native count again to
the decoded cloud, its file and the decoding time (+50 % points), and on the real KITTI and Ouster submaps it
gained 0.002-0.009 IoU (BENCHMARKS.md, "Decode post-filter")."""


PLANE_NEIGHBOURS = 48
"""The planes of the spread when it comes without snapping, and the snapping planes of CANDIDATES: each point's 48
nearest decoded points (about a 15-30 cm disk at the decoder's native density)."""

PLANE_ANCHOR_EVERY = 2
"""Planes are fitted at every second decoded point (`local_planes`); the others take their nearest one's: 40 % less
filter time than a plane per point, for about 0.003 less IoU on the real KITTI and Ouster submaps."""


def setting_byte(snap: int = 0, spread: int = 0, isolated: bool = False) -> int:
    """The post-filter byte of field values (snap and spread: indices into SNAP_NEIGHBOURS and SPREAD)."""
    return snap | spread << 2 | (_ISOLATED_BIT if isolated else 0)


CANDIDATES = (
    OFF,
    setting_byte(snap=3, spread=1),
    setting_byte(snap=3, spread=3),
    setting_byte(snap=3, spread=1, isolated=True),
    setting_byte(snap=3, spread=3, isolated=True),
)
"""Settings the encoder tries on each network tile (all share one plane fit): of a grid of 11 settings tried on
the real KITTI and Ouster submaps with e0..e3, those that were the best for some model under the rule of
`choose_post_filter`."""

MAX_D_E_INCREASE = 0.05
"""A setting is chosen only if the tile's D_e stays within this fraction above the unfiltered decode's."""


@dataclass(frozen=True)
class PostFilter:
    """A decoded post-filter byte."""

    snap_neighbours: int
    spread_copies: int
    spread_radius_m: float
    isolated: bool
    patch_levels: int = 0  # decoder levels per patch of patch planes (0: not patch planes)
    per_patch: bool = False  # patch choices: the patch operation's parameters are chosen per patch

    @classmethod
    def parse(cls, byte: int, label: str = "tile") -> "PostFilter":
        """ContainerError for a byte with unknown bits or patch planes combined with a neighbour-plane field."""
        if byte == PATCH_CHOICES:
            return cls(0, max(option[1] for option in PATCH_OPTIONS), max(option[2] for option in PATCH_OPTIONS),
                       False, PATCH_LEVELS, True)
        patch = 0 <= byte <= 255 and bool(byte & PATCH)
        if not 0 <= byte <= 255 or (byte & _NEIGHBOUR_BITS if patch else byte & ~_NEIGHBOUR_BITS):
            raise ContainerError(f"{label}: unknown post-filter setting 0x{byte:02x}")
        if patch:
            if byte & ~(PATCH | _PATCH_TWO_COPIES_BIT):
                raise ContainerError(f"{label}: unknown post-filter setting 0x{byte:02x}")
            return cls(0, PATCH_COPIES[bool(byte & _PATCH_TWO_COPIES_BIT)], PATCH_RADIUS_M, False, PATCH_LEVELS)
        copies, radius = SPREAD[byte >> 2 & 3]
        return cls(SNAP_NEIGHBOURS[byte & 3], copies, radius, bool(byte & _ISOLATED_BIT))


    def describe(self) -> str:
        """A few words for `info`, e.g. "patch planes, +2 points per point"."""
        if self.per_patch:
            return "patch planes chosen per patch"
        if self.patch_levels:
            return f"patch planes, +{self.spread_copies} point{'s' if self.spread_copies > 1 else ''} per point"
        parts = [f"{self.snap_neighbours}-point planes"] if self.snap_neighbours else []
        if self.spread_copies:
            parts.append(f"+{self.spread_copies} on {self.spread_radius_m * 100:g} cm disks")
        if self.isolated:
            parts.append("isolated points removed")
        return ", ".join(parts) or "off"


def check_setting(byte: int, label: str = "tile", version: int | None = None) -> int:
    """The byte, after ContainerError for unknown bits (and for patch planes in a container `version` before 5,
    patch choices before 6)."""
    setting = PostFilter.parse(byte, label)
    first = PATCH_CHOICE_VERSION if setting.per_patch else PATCH_VERSION
    if setting.patch_levels and version is not None and version < first:
        raise ContainerError(f"{label}: post-filter setting 0x{byte:02x} in a version {version} file")
    return byte


def apply_patch_filter(decoded: np.ndarray, byte: int, upsampling_factors, extent_m: np.ndarray,
                       compiled: bool = False) -> np.ndarray:
    """The tile's decoded points under the patch-plane setting `byte`: the network's whole (uncropped, in decoder
    order) (K, 3) output of a model with these upsampling factors reworked (`geometry.patchesnumpy.patch_planes`)
    and cropped to the tile's box [0, extent_m] as `tilepoints.keep_inside` crops (all clamped into it when none is
    inside); float32 metres. compiled=True runs numba's kernel of it (`geometry.patches`: the same bytes in about
    half the time, but loading numba costs a process ~120 MB and 0.4-0.9 CPU-s), for the encoder, which loads
    numba anyway; the decoder runs numpy's."""
    if compiled:
        from mapsqueeze.geometry.patches import patch_planes
    else:
        from mapsqueeze.geometry.patchesnumpy import patch_planes

    setting = PostFilter.parse(byte)
    patch = int(np.prod(upsampling_factors[-setting.patch_levels:], dtype=np.int64))
    inside = patch_planes(decoded, patch, PATCH_STRENGTH, setting.spread_copies, PATCH_RADIUS_M, extent_m)
    if len(inside) or not len(decoded):
        return inside
    everything = patch_planes(decoded, patch, PATCH_STRENGTH, setting.spread_copies, PATCH_RADIUS_M)
    return np.clip(everything, np.float32(0), np.asarray(extent_m).astype(np.float32))


def choose_patch_filter(original_world: np.ndarray, uncropped: np.ndarray, plain: np.ndarray, upsampling_factors,
                        frame_m: np.ndarray, extent_m: np.ndarray, compiled: bool = True) -> int:
    """The setting byte of OFF and PATCH_CANDIDATES, in that order, whose output has the highest IoU with the
    tile's points (`metrics.iou`'s world-anchored grid), where two extra points per point must also gain
    PATCH_EXTRA_COPY_MIN_IOU_GAIN over one; ties go to the earlier, so OFF unless a setting gains.

    original_world: the tile's (N, 3) points in world metres; uncropped: the network's whole (K, 3) output (model
    with these upsampling factors) and plain: its points inside the tile's box [0, extent_m] (the paper's decode),
    both in tile-local metres relative to the world point `frame_m`. The candidates' outputs are marked on one
    occupancy grid as they are made (`occupancy.patch_setting_ious`), or made whole (`apply_patch_filter`) where
    that grid does not serve. compiled=False: numpy's versions of the kernels (`geometry.occupancynumpy`: the
    same IoUs without loading numba, for small maps)."""
    if compiled:
        from mapsqueeze.geometry.occupancy import occupancy_ious, patch_setting_ious  # numba: the encoder's alone
    else:
        from mapsqueeze.geometry.occupancynumpy import occupancy_ious, patch_setting_ious

    settings = (OFF, *PATCH_CANDIDATES)
    patch = int(np.prod(upsampling_factors[-PATCH_LEVELS:], dtype=np.int64))
    ious = patch_setting_ious(original_world, uncropped, patch, PATCH_STRENGTH, PATCH_COPIES, PATCH_RADIUS_M,
                              extent_m, frame_m, IOU_VOXEL_M)
    if ious is None:
        clouds = [plain] + [apply_patch_filter(uncropped, byte, upsampling_factors, extent_m, compiled=compiled)
                            for byte in PATCH_CANDIDATES]
        ious = occupancy_ious(original_world, clouds, frame_m, IOU_VOXEL_M) or \
            [iou(original_world, cloud.astype(np.float64) + frame_m) for cloud in clouds]  # a box too large for a grid
    best = 0
    for candidate in range(1, len(settings)):
        margin = PATCH_EXTRA_COPY_MIN_IOU_GAIN if candidate > 1 else 0.0
        if ious[candidate] >= ious[candidate - 1] + margin and ious[candidate] > ious[best]:
            best = candidate
    return settings[best]


def apply_patch_choices(decoded: np.ndarray, choices: np.ndarray, upsampling_factors, extent_m: np.ndarray
                        ) -> np.ndarray:
    """The tile's decoded points under patch choices: patch i (the points embedding point i spawned, consecutive
    rows) of the network's whole (uncropped, in decoder order) (K, 3) output reworked by PATCH_OPTIONS[choices[i]],
    cropped to the tile's box [0, extent_m] (all of them clamped into it when none is inside); float32 metres,
    patch after patch. Runs numpy (`geometry.patchesnumpy.patch_planes_chosen`: the bytes of `patches.patch_planes`
    on each patch alone, so that its disk samples do not depend on the other patches' options; the patches of one
    option at once), so that decoding loads no numba."""
    from mapsqueeze.geometry.patchesnumpy import patch_planes_chosen

    patch = int(np.prod(upsampling_factors, dtype=np.int64))
    if len(decoded) != patch * len(choices):
        raise ValueError(f"{len(choices)} patch choices for {len(decoded)} points in patches of {patch}")
    for box in (extent_m, None):
        cloud = patch_planes_chosen(decoded, patch, PATCH_OPTIONS, choices, box)
        if box is not None and (len(cloud) or not len(decoded)):
            return cloud
    return np.clip(cloud, np.float32(0), np.asarray(extent_m).astype(np.float32))


def encode_patch_choices(choices: np.ndarray) -> bytes:
    """The payload prefix of patch choices: varint stream length, then the stream (varint count of choices, their
    histogram, `entropy.Histogram`, and their ANS words)."""
    choices = np.asarray(choices, dtype=np.int64)
    histogram = Histogram.fit(choices)
    symbols = SymbolWriter()
    symbols.histogram(choices, histogram)
    head = ByteWriter()
    head.varint(len(choices))
    histogram.write(head)
    stream = head.getvalue() + symbols.getvalue()
    prefix = ByteWriter()
    prefix.varint(len(stream))
    return prefix.getvalue() + stream


def split_patch_choices(payload: bytes, label: str) -> tuple[bytes, bytes]:
    """(choice stream, the rest: the latent payload) of a patch-choice tile's payload; ContainerError when the
    stream's length does not fit in it."""
    reader = ByteReader(payload, f"{label}: patch choices")
    stream = reader.raw(reader.varint(limit=len(payload) + 1))
    return stream, reader.raw(reader.remaining)


def decode_patch_choices(stream: bytes, n_patches: int, label: str) -> np.ndarray:
    """The (n_patches,) option indices of a choice stream (`encode_patch_choices`); ContainerError when it is
    corrupt, holds other than n_patches symbols or names an option outside PATCH_OPTIONS."""
    reader = ByteReader(stream, f"{label}: patch choices")
    count = reader.varint(limit=2**32)
    if count != n_patches:
        raise reader.fail(f"{count} choices for {n_patches} patches")
    histogram = Histogram.read(reader)
    if not 0 <= histogram.low < len(PATCH_OPTIONS) or histogram.span > 2 * len(PATCH_OPTIONS):
        raise reader.fail(f"choice alphabet {histogram.low}..{histogram.low + histogram.span - 1} beyond the "
                          f"{len(PATCH_OPTIONS)} options")
    symbols = SymbolReader(reader.raw(reader.remaining), f"{label}: patch choices")
    try:
        choices = symbols.histogram(histogram, n_patches)
    except (ValueError, RuntimeError) as exc:
        raise reader.fail(f"undecodable choice stream ({exc})") from None
    symbols.finish()
    if len(choices) and (choices.min() < 0 or choices.max() >= len(PATCH_OPTIONS)):
        raise reader.fail(f"choice beyond the {len(PATCH_OPTIONS)} options")
    return choices


def start_option(byte: int) -> int:
    """The patch option equal to a tile's OFF or patch-plane setting (up to the disk samples' numbering)."""
    setting = PostFilter.parse(byte)
    if byte == OFF:
        return 0
    if not setting.patch_levels or setting.per_patch:
        raise ValueError(f"post-filter setting 0x{byte:02x} has no patch option")
    return PATCH_OPTIONS.index((PATCH_STRENGTH, setting.spread_copies, PATCH_RADIUS_M))


@dataclass(frozen=True)
class PatchChoiceSearch:
    """The result of `search_patch_choices` on one tile."""

    choices: np.ndarray  # (n_patches,) uint8 option indices (PATCH_OPTIONS; compress holds them for every tile)
    before: float  # IoU with every patch under the start option
    after: float  # IoU with the choices


def search_patch_choices(original_world: np.ndarray, uncropped: np.ndarray, upsampling_factors, frame_m: np.ndarray,
                         extent_m: np.ndarray, byte: int, copy_weight: float = 0.0, payload_bytes: int = 0,
                         compiled: bool = True) -> PatchChoiceSearch | None:
    """The tile's patch choices (one per embedding point) of a greedy search (`occupancy.patch_option_ious`,
    PATCH_CHOICE_SWEEPS sweeps from the option of setting `byte`) for the highest IoU with the tile's
    points, or, with a model's `copy_weight` > 0 (`ModelConfig.patch_choice_copy_weight`), for that weighed IoU and
    then PATCH_CHOICE_RATE_SWEEPS sweeps charging each bit of the choices IOU_PER_LOG_RATE / (8 payload_bytes), the
    network payload's bytes (none when 0); None when the tile's voxel box is too large for the search
    (`patch_choice_prefix` decides whether they pay).

    original_world: the tile's (N, 3) points in world metres; uncropped: the network's whole (K, 3) output for the
    embedding the decoder sees, in its order, tile-local metres relative to the world point `frame_m`.
    compiled=False: numpy's version of the search (`geometry.occupancynumpy`: the same choices without numba)."""
    if compiled:
        from mapsqueeze.geometry.occupancy import patch_option_ious  # numba: loaded only where choices are searched
    else:
        from mapsqueeze.geometry.occupancynumpy import patch_option_ious

    patch = int(np.prod(upsampling_factors, dtype=np.int64))  # the points of one embedding point
    start = np.full(len(uncropped) // patch, start_option(byte), dtype=np.int64)
    rated = copy_weight > 0 and payload_bytes > 0
    found = patch_option_ious(original_world, uncropped, patch, PATCH_OPTIONS, extent_m, start, frame_m,
                              IOU_VOXEL_M, PATCH_CHOICE_SWEEPS, copy_weight,
                              IOU_PER_LOG_RATE / (8 * payload_bytes) if rated else 0.0,
                              PATCH_CHOICE_RATE_SWEEPS if rated else 0)
    if found is None:
        return None
    choices, before, after = found
    return PatchChoiceSearch(choices.astype(np.uint8), before, after)


def patch_choice_prefix(search: PatchChoiceSearch, payload_bytes: int) -> bytes | None:
    """The payload prefix of the searched choices (`encode_patch_choices`) where they pay: their IoU gain exceeds
    IOU_PER_LOG_RATE x ln((payload_bytes + prefix bytes) / payload_bytes); else None."""
    prefix = encode_patch_choices(search.choices)
    if search.after - search.before <= IOU_PER_LOG_RATE * np.log((payload_bytes + len(prefix)) / payload_bytes):
        return None
    return prefix


def choices_pay_clearly(search: PatchChoiceSearch | None, payload_bytes: int) -> bool:
    """Whether a tile's searched patch choices would pay (`patch_choice_prefix`) even for a network payload of
    CLEAR_PAY_FRACTION of its `payload_bytes`; False without a search."""
    if search is None:
        return False
    return patch_choice_prefix(search, max(1, int(payload_bytes * CLEAR_PAY_FRACTION))) is not None


def apply_post_filter(cloud: np.ndarray, byte: int, planes: tuple[np.ndarray, np.ndarray] | None = None
                      ) -> np.ndarray:
    """A decoded (K, 3) float32 tile cloud (tile-local metres) after the post-filter `byte`, float32; byte 0 and
    clouds of fewer than 3 points are returned as they are. `planes`: `local_planes(cloud, k)` already computed for
    the byte's k, to share them between settings. The result may leave the tile's box (the caller crops it)."""
    setting = PostFilter.parse(byte)
    if setting.patch_levels:
        raise ValueError("the patch-plane setting applies to the uncropped decode: apply_patch_filter")
    if byte == OFF or len(cloud) < 3:
        return cloud
    points = np.asarray(cloud, dtype=np.float64)
    if setting.snap_neighbours or setting.spread_copies:
        k = setting.snap_neighbours or PLANE_NEIGHBOURS
        centroids, normals = planes if planes is not None else local_planes(points, k, PLANE_ANCHOR_EVERY)
        if setting.snap_neighbours:
            points = project_to_planes(points, centroids, normals)
        if setting.spread_copies:
            points = np.concatenate([points, disk_samples(points, normals, setting.spread_radius_m,
                                                          setting.spread_copies)])
    if setting.isolated:
        keep = keep_supported(points, ISOLATED_RADIUS_M, ISOLATED_MIN_NEIGHBOURS)
        if keep.any():
            points = points[keep]
    return points.astype(np.float32)


def choose_post_filter(original: np.ndarray, decoded: np.ndarray, frame_m: np.ndarray, crop) -> tuple[int, float]:
    """(setting byte, D_e in metres of the filtered decode) for one network tile: of CANDIDATES whose D_e is at most
    (1 + MAX_D_E_INCREASE) x the unfiltered decode's, the one with the highest IoU (on the metric's world-anchored
    grid, `metrics.iou`); ties go to the earlier candidate, so OFF unless a setting gains.

    original: the tile's (N, 3) points and decoded: its (K, 3) decoded points, both tile-local metres relative to
    the world point `frame_m`; crop(cloud) -> the cloud's points the decoder keeps (inside the tile's box).
    """
    original = np.asarray(original, dtype=np.float64)
    original_tree = nearest_tree(original)
    world = original + frame_m
    planes = (local_planes(np.asarray(decoded, dtype=np.float64), PLANE_NEIGHBOURS, PLANE_ANCHOR_EVERY)
              if len(decoded) >= 3 else None)
    best = limit = None
    for byte in CANDIDATES:
        filtered = crop(apply_post_filter(decoded, byte, planes))
        d_e = d_euclidean(original, filtered, original_tree)
        if limit is None:
            limit = d_e * (1 + MAX_D_E_INCREASE)
        elif d_e > limit:
            continue
        overlap = iou(world, filtered.astype(np.float64) + frame_m)
        if best is None or overlap > best[0]:
            best = (overlap, byte, d_e)
    return best[1], best[2]
