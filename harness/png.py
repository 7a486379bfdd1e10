"""Whether bytes are a whole PNG file a viewer can show, checked before anything is
inflated or decoded.

The checks follow the PNG specification (W3C, *Portable Network Graphics (PNG)
Specification*, 3rd ed.) and what libpng 1.6, the reader of most viewers, refuses:
chunk framing and CRCs, the header's sizes and sample formats, the order and number of
critical chunks, a whole palette, and pixel data that inflates to exactly the scanlines
the header declares. Pillow then decodes what passed. The study pages
(:mod:`analysis.study_data`) check their figures with it and the ``mask`` domain
(:mod:`harness.domains.mask`) its image.
"""

from __future__ import annotations

import struct
import zlib

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
"""The first bytes of every PNG file."""


def png_problem(data: bytes) -> str:
    """What makes ``data`` other than a whole PNG file a viewer can show, in words (empty
    when nothing does).

    In order: the signature; at most :data:`MAX_CHUNKS` chunks, each of a length that
    fits in the file and a matching CRC-32; ``IHDR`` first (13 bytes: a width and height
    from 1 to :data:`MAX_SIDE`, a colour type with one of its allowed bit depths,
    compression and filter methods 0, interlace 0 or 1); every later chunk one libpng
    reads (:func:`chunk_problem`); ``PLTE`` before the pixels of a palette image; the
    ``IDAT`` chunks consecutive; ``IEND`` last with nothing after it. Then the ``IDAT``
    data must inflate (:func:`pixels_problem`) to exactly the scanlines ``IHDR``
    declares, each with a known filter type, so a damaged stream under recomputed CRCs
    is found too. Last, Pillow (matplotlib's reader of PNG files) must decode it.
    Nothing is inflated or decoded before the declared image is known to be within the
    pixel budget.
    """
    if not data.startswith(PNG_SIGNATURE):
        return "no PNG signature"
    at, header = len(PNG_SIGNATURE), b""
    stream: list[bytes] = []
    kinds: list[bytes] = []
    while True:
        if len(kinds) >= MAX_CHUNKS:
            return f"more than {MAX_CHUNKS} chunks"
        if at + 12 > len(data):
            return f"cut short at byte {at} (no IEND chunk)"
        length, kind = struct.unpack(">I4s", data[at : at + 8])
        end = at + 12 + length
        if length > 0x7FFFFFFF or end > len(data):
            return f"a chunk at byte {at} runs past the end of the file (cut short)"
        body = data[at + 8 : end - 4]
        if zlib.crc32(data[at + 4 : end - 4]) != struct.unpack(">I", data[end - 4 : end])[0]:
            return f"the {kind[:4]!r} chunk at byte {at} fails its CRC (damaged)"
        if not kinds:
            if kind != b"IHDR" or length != 13:
                return "its first chunk is not a 13-byte IHDR"
            problem = header_problem(body)
            if problem:
                return problem
            header = body
        else:
            problem = chunk_problem(kind, body, header, kinds)
            if problem:
                return f"{problem} (chunk at byte {at})"
        if kind == b"IDAT":
            if stream and kinds[-1] != b"IDAT":
                return "its IDAT chunks are not consecutive"
            stream.append(body)
        kinds.append(kind)
        at = end
        if kind == b"IEND":
            break
    if not stream:
        return "no IDAT chunk (no pixels)"
    if at != len(data):
        return f"{len(data) - at} bytes after its IEND chunk"
    if header[9] == 3 and (b"PLTE" not in kinds or kinds.index(b"PLTE") > kinds.index(b"IDAT")):
        return "a palette image without a PLTE chunk before its pixels"
    return pixels_problem(header, b"".join(stream)) or decoder_problem(data)


def chunk_problem(kind: bytes, body: bytes, header: bytes, before: list[bytes]) -> str:
    """What libpng would refuse in a chunk after ``IHDR``, in words (empty when nothing).

    The chunk type is four ASCII letters; a critical chunk (first letter upper case) is
    one of ``IHDR``, ``PLTE``, ``IDAT``, ``IEND``, and ``IHDR`` comes only first; ``PLTE``
    comes at most once, before the pixels, never in a grey image, with 1 to
    ``2^depth`` (at most 256) entries of 3 bytes.

    Args:
        kind: The chunk's type (4 bytes).
        body: The chunk's data.
        header: The 13-byte ``IHDR`` body, already checked.
        before: The types of the chunks before it, in order.
    """
    if not all(65 <= c <= 90 or 97 <= c <= 122 for c in kind):
        return f"a chunk type {kind!r} that is not four ASCII letters"
    if kind[0] <= 90 and kind not in CRITICAL:
        return f"an unknown critical chunk {kind.decode()}"
    if kind == b"IHDR":
        return "a second IHDR"
    if kind == b"PLTE":
        depth, colour = header[8], header[9]
        entries = min(256, 1 << depth) if colour == 3 else 256
        if b"PLTE" in before:
            return "a second PLTE"
        if b"IDAT" in before:
            return "a PLTE after the pixels"
        if colour in (0, 4):
            return "a PLTE in a grey image"
        if not body or len(body) % 3 or len(body) // 3 > entries:
            return f"a PLTE of {len(body)} bytes (PNG allows 3 to {3 * entries} in steps of 3)"
    return ""


CRITICAL = (b"IHDR", b"PLTE", b"IDAT", b"IEND")
"""The critical chunk types PNG defines; a viewer refuses any other critical chunk."""

MAX_CHUNKS = 1 << 14
"""Most chunks read from one PNG: a 64 MiB figure in 8 KiB IDATs has 8192; bounds the
time spent on a file of millions of tiny chunks."""

MAX_SIDE = 4096
"""Largest width or height accepted (pixels; libpng's own default limit is 10^6)."""

MAX_FIGURE_PIXELS = MAX_SIDE * MAX_SIDE
"""Largest figure accepted (pixels): about 16.8 million, 4096 x 4096; a study's figure
has about 1.5 million. Bounds what inflating and decoding one may allocate."""

CHANNELS = {0: 1, 2: 3, 3: 1, 4: 2, 6: 4}
"""Samples per pixel of each PNG colour type (grey, RGB, palette, grey + alpha, RGBA)."""

DEPTHS = {0: (1, 2, 4, 8, 16), 2: (8, 16), 3: (1, 2, 4, 8), 4: (8, 16), 6: (8, 16)}
"""The bit depths the PNG specification allows for each colour type."""

ADAM7 = (
    (0, 0, 8, 8),
    (4, 0, 8, 8),
    (0, 4, 4, 8),
    (2, 0, 4, 4),
    (0, 2, 2, 4),
    (1, 0, 2, 2),
    (0, 1, 1, 2),
)
"""The seven passes of an interlaced PNG: first column, first row, column step, row step."""


def header_problem(header: bytes) -> str:
    """What is wrong with a 13-byte ``IHDR`` body (empty when nothing is)."""
    width, height, depth, colour, compression, method, interlace = struct.unpack(">IIBBBBB", header)
    if not (0 < width <= MAX_SIDE and 0 < height <= MAX_SIDE):
        return f"an image of {width} x {height} pixels (each side 1 to {MAX_SIDE} allowed)"
    if depth not in DEPTHS.get(colour, ()):
        return (
            f"IHDR declares colour type {colour} with bit depth {depth}, which PNG does not allow"
        )
    if compression != 0 or method != 0 or interlace not in (0, 1):
        return (
            f"IHDR declares compression method {compression}, filter method {method}, "
            f"interlace {interlace} (PNG allows 0, 0 and 0 or 1)"
        )
    return ""


def scanlines(header: bytes) -> list[tuple[int, int]]:
    """``(rows, bytes per row including the filter byte)`` of each pass of the image
    ``header`` declares (one pass for a plain image, the seven Adam7 passes for an
    interlaced one; passes without pixels left out).
    """
    width, height, depth, colour, _, _, interlace = struct.unpack(">IIBBBBB", header)
    bits = CHANNELS[colour] * depth
    out = []
    for x0, y0, dx, dy in ADAM7 if interlace else ((0, 0, 1, 1),):
        columns, rows = -(-(width - x0) // dx), -(-(height - y0) // dy)
        if columns > 0 and rows > 0:
            out.append((rows, 1 + -(-columns * bits // 8)))
    return out


def pixels_problem(header: bytes, stream: bytes) -> str:
    """What is wrong with a PNG's concatenated ``IDAT`` data, in words (empty when
    nothing is).

    The data must be one zlib stream (its Adler-32 checked by ``zlib``) that inflates to
    exactly the bytes of :func:`scanlines` (``rows * (1 + ceil(columns * bits per pixel
    / 8))`` summed over the passes), every scanline starting with a filter type 0 to 4.
    Inflation stops one byte past the declared size, which ``IHDR``'s checks
    (:func:`header_problem`) keep within :data:`MAX_FIGURE_PIXELS` pixels.

    Args:
        header: The 13-byte ``IHDR`` body, already checked.
        stream: The ``IDAT`` chunks' data, joined in order.
    """
    passes = scanlines(header)
    size = sum(rows * row for rows, row in passes)
    inflater = zlib.decompressobj()
    try:
        pixels = inflater.decompress(stream, size + 1)
    except zlib.error as error:
        return f"its pixel data does not inflate ({error}; damaged)"
    if len(pixels) != size or not inflater.eof or inflater.unused_data:
        return f"its pixel data is not the {size} bytes IHDR declares (damaged)"
    at = 0
    for rows, row in passes:
        if any(pixels[at + k * row] > 4 for k in range(rows)):
            return "a scanline with an unknown filter type (damaged)"
        at += rows * row
    return ""


def decoder_problem(data: bytes) -> str:
    """What Pillow, the decoder matplotlib reads PNG files with, says of ``data`` (empty
    when it decodes the whole image). Called only on a file whose pixel count is
    within :data:`MAX_FIGURE_PIXELS`.
    """
    import io

    from PIL import Image

    try:
        with Image.open(io.BytesIO(data)) as image:
            image.load()
    except Exception as err:  # any refusal of the decoder: the figure could not be shown
        return f"Pillow cannot decode it ({type(err).__name__}: {str(err)[:120]})"
    return ""
