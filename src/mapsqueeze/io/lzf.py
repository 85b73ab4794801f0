"""LZF decompression (Marc Lehmann's liblzf format, the one PCL's DATA binary_compressed PCD files use).

A stream is a sequence of tokens, each starting with a control byte `ctrl`:
- ctrl < 32: a literal run, the next ctrl + 1 bytes copied as they are;
- else a back-reference: length (ctrl >> 5) + 2, where a length field of 7 takes one more byte added to it, then
  one byte `low`; the bytes come from ((ctrl & 31) << 8) + low + 1 bytes back in the output. A reference reaching
  into the bytes it writes (distance < length) repeats its last `distance` bytes.
"""

MAX_EXPANSION = 88
"""Most output bytes per input byte: a 3-byte reference (ctrl, extra length, offset) writes at most 7 + 255 + 2 =
264 bytes; literals write fewer bytes than they take."""


class LZFError(ValueError):
    """An LZF stream is corrupt: a token runs past its input, reaches before the output's start or past its end, or
    the output ends at another size than expected."""


COMPILED_BYTES = 8 << 20
"""Blocks of at least this many bytes (decompressed) are decoded by the compiled kernel (`io.lzfcompiled`: 4 MB of
float32 coordinates in 0.009 s instead of 0.30 s; loading numba costs a process ~0.5 CPU-s, what the pure-Python
loop spends on ~8 MB)."""

LITERAL_PAST_END, OUTPUT_OVERFLOW, REFERENCE_PAST_END, BEFORE_START, SIZE_MISMATCH = range(1, 6)
"""What went wrong in a corrupt stream: the codes both decoders report (`_error`)."""


def decompress(data: bytes | memoryview, size: int, compiled: bool | None = None) -> bytearray:
    """The `size` bytes LZF stream `data` decompresses to; raises LZFError unless it decompresses to exactly `size`
    bytes. Only `size` bytes are allocated, and every copy is bounds-checked against both buffers first.

    compiled None: the compiled kernel for blocks of COMPILED_BYTES or more, else pure Python; the same bytes and
    errors either way. Pure Python: slice copies for literal runs and for references that do not overlap their
    output, a repeated pattern for those that do: ~0.6 us a token. The binary_compressed block of a 131,072-point
    PCD of float32 x, y, z, intensity (two KITTI scans; 1,827,636 bytes, 82,012 literal runs and 155,940 references,
    decompressing to 2,097,152) decodes in 0.14 s.
    """
    if compiled if compiled is not None else size >= COMPILED_BYTES:
        import numpy as np

        from mapsqueeze.io.lzfcompiled import decompress_into

        out = bytearray(size)
        status, token, value, written = decompress_into(np.frombuffer(data, dtype=np.uint8),
                                                        np.frombuffer(out, dtype=np.uint8))
        if status:
            raise _error(status, token, value, written, len(data), size)
        return out
    out = bytearray(size)
    end = len(data)
    position = written = 0
    while position < end:
        token, ctrl = position, data[position]
        position += 1
        if ctrl < 32:  # literal run
            length = ctrl + 1
            if position + length > end:
                raise _error(LITERAL_PAST_END, token, length, written, end, size)
            if written + length > size:
                raise _error(OUTPUT_OVERFLOW, token, length, written, end, size)
            out[written : written + length] = data[position : position + length]
            position += length
            written += length
            continue
        length = ctrl >> 5
        if position + (length == 7) >= end:
            raise _error(REFERENCE_PAST_END, token, 0, written, end, size)
        if length == 7:
            length += data[position]
            position += 1
        length += 2
        distance = ((ctrl & 31) << 8) + data[position] + 1
        position += 1
        start = written - distance
        if start < 0:
            raise _error(BEFORE_START, token, distance, written, end, size)
        if written + length > size:
            raise _error(OUTPUT_OVERFLOW, token, length, written, end, size)
        if distance >= length:
            out[written : written + length] = out[start : start + length]
        else:  # overlapping: the last `distance` bytes repeated
            repeats = -(-length // distance)
            out[written : written + length] = (out[start:written] * repeats)[:length]
        written += length
    if written != size:
        raise _error(SIZE_MISMATCH, end, 0, written, end, size)
    return out


def _error(status: int, token: int, value: int, written: int, end: int, size: int) -> LZFError:
    """The error of a decoder's status: at input byte `token`, `value` the run's length or the reference's
    distance, `written` the output bytes so far, `end` the stream's length, `size` the output's."""
    if status == LITERAL_PAST_END:
        return LZFError(f"a literal run of {value} bytes at byte {token:,} runs past the end of the {end:,}-byte "
                        "stream")
    if status == OUTPUT_OVERFLOW:
        return LZFError(f"the stream decompresses to more than the {size:,} bytes expected")
    if status == REFERENCE_PAST_END:
        return LZFError(f"a back-reference at byte {token:,} runs past the end of the {end:,}-byte stream")
    if status == BEFORE_START:
        return LZFError(f"a back-reference at byte {token:,} points {value:,} bytes back from output byte "
                        f"{written:,}, before the start")
    return LZFError(f"the stream decompresses to {written:,} bytes, {size:,} expected")
