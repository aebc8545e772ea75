"""An encoded image's size from its header alone (JPEG frame header, PNG IHDR chunk), and
whether its stream is whole (it ends with the format's end marker).

Sources compare the size with the calibration before anything decodes the image: a crafted header
can declare gigapixels, and a decoder would allocate them. The readers take a ``read(n) -> bytes``
callable (``io.BytesIO(data).read`` for bytes in memory, ``file.read`` for a file), so a file's
size is known after reading its first segments only.

:func:`end_problem` reads the last bytes only: a stream cut short (a truncated file, a record
rewritten with half an image) does not end with the marker, where a decoder may fill the missing
rows with grey and report success (libjpeg only warns; OpenCV 4 returns that image). A stream cut
and given a new end marker still passes: every decoder reads it, grey below the cut.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from numpy.typing import NDArray

#: JPEG start-of-frame markers (baseline, progressive, lossless, arithmetic): they hold the size.
_JPEG_SOF_MARKERS = frozenset(range(0xC0, 0xD0)) - {0xC4, 0xC8, 0xCC}
#: JPEG markers without a length field (restart markers, TEM).
_JPEG_BARE_MARKERS = frozenset(range(0xD0, 0xD8)) | {0x01}
_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
#: The last bytes of a whole stream: JPEG's end-of-image marker, PNG's empty IEND chunk (with its CRC).
JPEG_END = b"\xff\xd9"
PNG_END = b"\x00\x00\x00\x00IEND\xaeB`\x82"

Read = Callable[[int], bytes]


def jpeg_size(read: Read) -> tuple[int, int]:
    """(width, height) in pixels from the first frame header of a JPEG stream; raises ValueError
    saying what is wrong (no start marker, a truncated segment, no frame header before the scan)."""
    if read(2) != b"\xff\xd8":
        raise ValueError("no JPEG start-of-image marker")
    while True:
        byte = read(1)
        if byte != b"\xff":
            raise ValueError("a segment does not start with a marker" if byte else "no frame header")
        marker = read(1)
        while marker == b"\xff":  # fill bytes
            marker = read(1)
        if not marker:
            raise ValueError("no frame header")
        code = marker[0]
        if code in _JPEG_BARE_MARKERS:
            continue
        if code in (0xD8, 0xD9, 0xDA):  # a second start, the end, or the scan before a frame header
            raise ValueError("no frame header before the image data")
        length_bytes = read(2)
        length = int.from_bytes(length_bytes, "big")
        if len(length_bytes) < 2 or length < 2:
            raise ValueError("a truncated segment")
        segment = read(length - 2)
        if len(segment) < length - 2:
            raise ValueError("a truncated segment")
        if code in _JPEG_SOF_MARKERS:
            if len(segment) < 5:
                raise ValueError("a truncated frame header")
            height, width = int.from_bytes(segment[1:3], "big"), int.from_bytes(segment[3:5], "big")
            if width == 0 or height == 0:
                raise ValueError(f"the frame header gives the size {width}x{height}")
            return width, height


def png_size(read: Read) -> tuple[int, int]:
    """(width, height) in pixels from a PNG stream's IHDR chunk; raises ValueError if there is none."""
    head = read(24)
    if len(head) < 24 or head[:8] != _PNG_SIGNATURE or head[12:16] != b"IHDR":
        raise ValueError("no PNG signature and IHDR chunk")
    width, height = int.from_bytes(head[16:20], "big"), int.from_bytes(head[20:24], "big")
    if width == 0 or height == 0:
        raise ValueError(f"the IHDR chunk gives the size {width}x{height}")
    return width, height


def end_problem(data: bytes | memoryview | NDArray[np.uint8]) -> str | None:
    """What shows that encoded image bytes are not a whole JPEG or PNG stream, or None.

    The format is the one the first bytes name (as decoders choose it): a JPEG must end with its
    end-of-image marker (FF D9), a PNG with its IEND chunk. Reads the first 8 and last 12 bytes.
    """
    head, tail = bytes(data[:8]), bytes(data[-len(PNG_END) :])
    if head[:2] == b"\xff\xd8":
        whole, marker = tail.endswith(JPEG_END), "JPEG end-of-image marker FF D9"
    elif head == _PNG_SIGNATURE:
        whole, marker = tail == PNG_END, "PNG IEND chunk"
    else:
        return "are neither a JPEG nor a PNG stream"
    return None if whole else f"end without the {marker} (cut short)"
