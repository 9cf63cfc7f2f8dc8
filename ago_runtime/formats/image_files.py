"""Decoding JPEG / PNG files safely: size read from the header first, corrupt data refused.

`decode_image(data, path, flags)` -> the cv2.imdecode array (BGR for colour), after two checks:

1. **Size before decoding.** The width and height are read from the file header (JPEG: the SOFn
   frame header; PNG: IHDR) and refused above `max_image_pixels()` pixels (default
   MAX_IMAGE_PIXELS = 50 megapixels, 8192 x 6100; nuScenes images are 1.44 MP) or above
   MAX_IMAGE_SIDE = 16384 pixels on a side. A 66 KB JPEG whose header claims 30000 x 16875 would
   otherwise be decoded into 1.5 GB of pixels (and more in the resize). `AGO_MAX_IMAGE_PIXELS`
   raises or lowers the limit.
2. **Corrupt data.** libjpeg and libpng, which OpenCV uses, *warn* about damaged data (scrambled
   entropy-coded bytes, a truncated scan, a bad CRC) on stderr and still return an image.
   `decode_image` captures what the decoder writes to the process's stderr (file descriptor 2)
   during the call and refuses the file when it says "Corrupt JPEG data", "Premature end of JPEG
   file" or a libpng error/CRC warning; any other decoder message is passed on to stderr.
   Scrambles that decode with no decoder message at all (the Huffman decoder fell back in step) are
   not caught; how many that is: benchmarks/results/corrupt_jpeg.md.
   (The capture swaps fd 2 for the duration of one decode: not meant for decoding from several
   threads at once.)

Every problem raises AgoInputError naming the file.
"""

from __future__ import annotations

import os
import struct
import sys
import tempfile
from pathlib import Path

import cv2
import numpy as np

from ago_runtime.errors import AgoInputError

MAX_IMAGE_PIXELS = 50_000_000
MAX_IMAGE_SIDE = 16384
ENV_MAX_PIXELS = "AGO_MAX_IMAGE_PIXELS"
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
# SOFn markers (baseline, extended, progressive, lossless; Huffman and arithmetic) carry the frame size.
_SOF_MARKERS = {0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF}
_CORRUPT_SIGNS = ("corrupt jpeg data", "premature end of jpeg file", "libpng error", "crc error",
                  "invalid jpeg file structure")


def max_image_pixels() -> int:
    env = os.environ.get(ENV_MAX_PIXELS)
    if env:
        try:
            return max(1, int(float(env)))
        except ValueError:
            raise AgoInputError(f"${ENV_MAX_PIXELS}", f"must be a number of pixels, got {env!r}") from None
    return MAX_IMAGE_PIXELS


def jpeg_size(data: bytes, path) -> tuple[int, int]:
    """(width, height) from a JPEG's frame header (the first SOFn segment before the scan)."""
    if data[:2] != b"\xff\xd8":
        raise AgoInputError(path, "not a JPEG file (no start-of-image marker)")
    i, n = 2, len(data)
    while i + 4 <= n:
        if data[i] != 0xFF:
            raise AgoInputError(path, f"corrupt JPEG header (no marker at byte {i})")
        marker = data[i + 1]
        if marker == 0xFF:            # fill byte
            i += 1
            continue
        if marker in (0x01,) or 0xD0 <= marker <= 0xD7:   # markers without a length
            i += 2
            continue
        if marker in (0xD9, 0xDA):   # end of image / start of scan before any frame header
            break
        (length,) = struct.unpack(">H", data[i + 2:i + 4])
        if length < 2:
            raise AgoInputError(path, f"corrupt JPEG header (segment length {length} at byte {i})")
        if marker in _SOF_MARKERS:
            if i + 9 > n:
                break
            height, width = struct.unpack(">HH", data[i + 5:i + 9])
            if width == 0 or height == 0:
                raise AgoInputError(path, f"JPEG frame header gives a size of {width}x{height}")
            return int(width), int(height)
        i += 2 + length
    raise AgoInputError(path, "corrupt or truncated JPEG (no frame header before the image data)")


def png_size(data: bytes, path) -> tuple[int, int]:
    """(width, height) from a PNG's IHDR chunk."""
    if data[:8] != PNG_SIGNATURE:
        raise AgoInputError(path, "not a PNG file (no PNG signature)")
    if len(data) < 24 or data[12:16] != b"IHDR":
        raise AgoInputError(path, "corrupt PNG (no IHDR header)")
    width, height = struct.unpack(">II", data[16:24])
    if width == 0 or height == 0:
        raise AgoInputError(path, f"PNG header gives a size of {width}x{height}")
    return int(width), int(height)


def header_size(data: bytes, path) -> tuple[int, int]:
    """(width, height) of a JPEG or PNG from its header, without decoding; AgoInputError otherwise."""
    if data[:2] == b"\xff\xd8":
        return jpeg_size(data, path)
    if data[:8] == PNG_SIGNATURE:
        return png_size(data, path)
    raise AgoInputError(path, "not a JPEG or PNG file")


def check_size(width: int, height: int, path) -> None:
    limit = max_image_pixels()
    if width > MAX_IMAGE_SIDE or height > MAX_IMAGE_SIDE or width * height > limit:
        raise AgoInputError(path, f"image header claims {width}x{height} pixels, more than ago decodes "
                                  f"(at most {MAX_IMAGE_SIDE} a side and {limit / 1e6:g} megapixels; "
                                  f"${ENV_MAX_PIXELS} sets the limit)")


def _imdecode_capturing_stderr(data: bytes, flags: int) -> tuple[np.ndarray | None, str]:
    """cv2.imdecode with file descriptor 2 redirected to a temporary file; gives (image, messages)."""
    try:
        sys.stderr.flush()
    except (AttributeError, ValueError):
        pass
    saved = os.dup(2)
    with tempfile.TemporaryFile() as capture:
        os.dup2(capture.fileno(), 2)
        try:
            img = cv2.imdecode(np.frombuffer(data, np.uint8), flags)
        finally:
            os.dup2(saved, 2)
            os.close(saved)
        capture.seek(0)
        text = capture.read().decode("utf-8", errors="replace")
    return img, text


def decode_image(data: bytes, path: str | Path, flags: int = cv2.IMREAD_COLOR) -> np.ndarray:
    """Decode JPEG/PNG bytes with cv2 after checking the header size; refuses corrupt data (module doc)."""
    width, height = header_size(data, path)
    check_size(width, height, path)
    img, messages = _imdecode_capturing_stderr(data, flags)
    lowered = messages.lower()
    sign = next((s for s in _CORRUPT_SIGNS if s in lowered), None)
    if sign is not None:
        first = next(ln for ln in messages.splitlines() if sign in ln.lower()).strip()
        raise AgoInputError(path, f"corrupt image data (decoder: {first[:160]})")
    if messages.strip():   # some other decoder note: not ours to swallow
        print(messages.rstrip(), file=sys.stderr)
    if img is None or img.size == 0:
        raise AgoInputError(path, "corrupt or unsupported image file (cv2 cannot decode it)")
    if img.shape[0] != height or img.shape[1] != width:
        raise AgoInputError(path, f"decoded size {img.shape[1]}x{img.shape[0]} differs from the header's "
                                  f"{width}x{height}")
    return img
