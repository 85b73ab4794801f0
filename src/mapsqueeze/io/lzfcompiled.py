"""`io.lzf.decompress` compiled (numba), for large blocks: the same bytes and the same error codes."""

import numpy as np

from mapsqueeze.geometry.jit import compiled
from mapsqueeze.io.lzf import BEFORE_START, LITERAL_PAST_END, OUTPUT_OVERFLOW, REFERENCE_PAST_END, SIZE_MISMATCH


@compiled
def decompress_into(data, out):
    """Decode the uint8 LZF stream `data` into the uint8 array `out`, every copy bounds-checked first; returns
    (status: 0 or an `io.lzf` error code, the token's input byte, the run's length or the reference's distance,
    output bytes written). A reference is copied byte by byte, so an overlapping one repeats its pattern."""
    end, size = data.shape[0], out.shape[0]
    position = written = 0
    while position < end:
        token = position
        ctrl = np.int64(data[position])
        position += 1
        if ctrl < 32:
            length = ctrl + 1
            if position + length > end:
                return LITERAL_PAST_END, token, length, written
            if written + length > size:
                return OUTPUT_OVERFLOW, token, length, written
            out[written:written + length] = data[position:position + length]
            position += length
            written += length
            continue
        length = ctrl >> 5
        if position + (1 if length == 7 else 0) >= end:
            return REFERENCE_PAST_END, token, 0, written
        if length == 7:
            length += np.int64(data[position])
            position += 1
        length += 2
        distance = ((ctrl & 31) << 8) + np.int64(data[position]) + 1
        position += 1
        start = written - distance
        if start < 0:
            return BEFORE_START, token, distance, written
        if written + length > size:
            return OUTPUT_OVERFLOW, token, length, written
        for i in range(length):
            out[written + i] = out[start + i]
        written += length
    if written != size:
        return SIZE_MISMATCH, end, 0, written
    return 0, 0, 0, written
