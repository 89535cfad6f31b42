"""Images: header checks before decoding (size, truncated JPEGs) and the RGB reader."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from ..errors import DataFormatError
from .arrays import _as_path


def check_image_header(path: str | Path, channels: int = 3) -> None:
    """Refuses a PNG (IHDR) or JPEG (start of frame) whose header claims more pixels than the memory limit allows.

    Other formats are left to the decoder (whose errors `load_rgb` / `load_depth` turn into
    `DataFormatError`).

    Raises:
        DataFormatError: a PNG signature with a header cut short.
        ProblemTooLargeError: the decoded image would exceed `gpdepth3d.limits.memory_limit`.
    """
    from ..limits import check_array_size

    path = Path(path)
    with open(path, "rb") as f:
        head = f.read(33)
        if head.startswith(b"\xff\xd8"):
            size = _jpeg_size(f)
            if size is not None:
                check_array_size(f"image {path}", (*size, channels), np.float64)
            return
    if not head.startswith(b"\x89PNG\r\n\x1a\n"):
        return
    if len(head) < 33 or head[12:16] != b"IHDR":
        raise DataFormatError(path, "corrupt PNG: no IHDR header")
    width, height = int.from_bytes(head[16:20], "big"), int.from_bytes(head[20:24], "big")
    check_array_size(f"image {path}", (height, width, channels), np.float64)


def _jpeg_size(f) -> tuple[int, int] | None:
    """(height, width) from a JPEG's start-of-frame marker, reading marker headers only (None: none found)."""
    f.seek(2)
    for _ in range(1000):  # the frame header comes after a few tables
        marker = f.read(2)
        if len(marker) < 2 or marker[0] != 0xFF:
            return None
        if marker[1] in (0xD8, 0x01) or 0xD0 <= marker[1] <= 0xD7:  # markers without a length
            continue
        length = f.read(2)
        if len(length) < 2:
            return None
        if 0xC0 <= marker[1] <= 0xCF and marker[1] not in (0xC4, 0xC8, 0xCC):  # SOFn
            frame = f.read(5)
            return (int.from_bytes(frame[1:3], "big"), int.from_bytes(frame[3:5], "big")) if len(frame) == 5 else None
        f.seek(int.from_bytes(length, "big") - 2, os.SEEK_CUR)
    return None


def _imread(path: Path, flags: int) -> np.ndarray | None:
    """cv2.imread with its size refusals and decoder errors as typed errors."""
    import cv2

    check_image_header(path)
    try:
        return cv2.imread(str(path), flags)
    except cv2.error as exc:
        raise DataFormatError(path, f"not a readable image: {str(exc).strip().splitlines()[-1]}") from None


def load_rgb(path: str | Path) -> np.ndarray:
    """Reads an image as (H, W, 3) uint8 RGB.

    Raises:
        DataFormatError: missing, unreadable, or truncated (JPEG) file.
    """
    import cv2

    path = _as_path(path)
    if not path.is_file():
        raise DataFormatError(path, "image not found")
    if path.suffix.lower() in (".jpg", ".jpeg"):
        _check_jpeg_complete(path)
    bgr = _imread(path, cv2.IMREAD_COLOR)
    if bgr is None:
        raise DataFormatError(path, "not a readable image")
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)


def _check_jpeg_complete(path: Path) -> None:
    """Refuses a truncated JPEG (OpenCV decodes one silently, greying the missing part).

    A complete JPEG starts with the SOI marker FFD8 and ends with the EOI marker FFD9 (trailing
    padding aside); inside the entropy-coded data an FF byte is always stuffed, so a file cut
    anywhere after its headers has no FFD9 at its end.
    """
    with open(path, "rb") as f:
        head = f.read(2)
        f.seek(0, os.SEEK_END)
        size = f.tell()
        f.seek(max(0, size - 4096))
        tail = f.read().rstrip(b"\x00\r\n\t ")
    if head != b"\xff\xd8":
        raise DataFormatError(path, "not a JPEG file (no FFD8 start marker)")
    if not tail.endswith(b"\xff\xd9"):
        raise DataFormatError(path, f"truncated JPEG ({size} bytes, no FFD9 end marker)")
    bad = _jpeg_marker_problem(path.read_bytes())
    if bad is not None:
        raise DataFormatError(path, f"corrupt JPEG data ({bad}): OpenCV would decode it silently into a wrong image")


def _jpeg_marker_problem(data: bytes) -> str | None:
    """The first marker no JPEG may hold (a reserved code, a segment past the end), or None.

    The file is walked segment by segment; in the entropy-coded data after each start of scan an
    FF byte is always followed by 00 (stuffing) or a restart marker D0-D7, else it starts the next
    marker. Random bytes in a scan soon give an FF followed by a reserved code (02-BF).
    """
    at, n = 2, len(data)
    while at < n:
        if data[at] != 0xFF:
            return f"byte {at}: expected a marker"
        while at + 1 < n and data[at + 1] == 0xFF:  # fill bytes before a marker
            at += 1
        if at + 1 >= n:
            return None
        code = data[at + 1]
        if code == 0xD9:  # end of image
            return None
        if 0x02 <= code <= 0xBF:
            return f"byte {at}: reserved marker FF{code:02X}"
        if 0xD0 <= code <= 0xD7 or code == 0x01:  # no length
            at += 2
            continue
        if at + 4 > n:
            return f"byte {at}: marker FF{code:02X} cut short"
        end = at + 2 + int.from_bytes(data[at + 2 : at + 4], "big")
        if end > n:
            return f"byte {at}: segment FF{code:02X} runs past the end of the file"
        at = end
        if code == 0xDA:  # start of scan: skip its entropy-coded data to the next marker
            while True:
                at = data.find(b"\xff", at)
                if at < 0 or at + 1 >= n:
                    return None
                if data[at + 1] == 0x00 or 0xD0 <= data[at + 1] <= 0xD7:
                    at += 2
                    continue
                break
    return None
