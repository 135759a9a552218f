"""A minimal MJPG AVI muxer that reports write errors.

``cv2.VideoWriter`` does not: on a full disk its ``write`` keeps returning True while
FFmpeg buffers the frames, ``release`` returns nothing, and the file is left cut
short without an index (``tests/data/test_avi.py`` shows this on a real full tmpfs).
A raw recording must fail loudly instead, so the chunks are written here: every
``write`` goes straight to the file and raises :class:`OSError` (ENOSPC, EFBIG) at
once. The layout is the plain AVI 1.0 RIFF form (``hdrl``, ``movi``, ``idx1``) that
OpenCV, FFmpeg and every player read.
"""

from __future__ import annotations

import os
import struct
from pathlib import Path

import cv2
import numpy as np

from beadsight.data.recording.logs import JPEG_QUALITY, RecordingError


class MjpgAviWriter:
    """A minimal MJPG AVI writer: every frame is a JPEG in a ``00dc`` chunk.

    Written in Python (not ``cv2.VideoWriter``) so that a write error -- disk full, file
    size limit -- raises OSError at once instead of being logged and ignored, and so the
    JPEG quality is explicit. :meth:`close` appends the ``idx1`` index and fills in the
    header sizes; a file cut short by a crash still reads (demuxers scan the ``movi``
    list) up to its last whole frame.
    """

    _AVIF_HASINDEX = 0x10
    _AVIIF_KEYFRAME = 0x10
    _PLACEHOLDER = 0  # header sizes before close(); readers fall back to scanning

    def __init__(
        self, path: Path, frame_hw: tuple[int, int], fps: float, quality: int = JPEG_QUALITY
    ):
        self.path = path
        self.height, self.width = frame_hw
        self.fps = float(fps)
        self.quality = int(quality)
        self.frames = 0
        self._index: list[tuple[int, int]] = []  # (offset from 'movi', size)
        self._max_size = 0
        self.failed = False  # a write failed: the file is cut short, close() only releases it
        self._f = open(path, "wb")  # noqa: SIM115 - closed in close()
        try:
            self._write_headers()
        except BaseException:
            self._f.close()
            raise

    def _avih(self) -> bytes:
        return struct.pack(
            "<10I16x",
            round(1e6 / self.fps),
            0,
            0,
            self._AVIF_HASINDEX,
            self.frames,
            0,
            1,
            self._max_size,
            self.width,
            self.height,
        )

    def _strh(self) -> bytes:
        rate = round(self.fps * 1000)
        return struct.pack(
            "<4s4sIHHIIIIIIIIhhhh",
            b"vids",
            b"MJPG",
            0,
            0,
            0,
            0,
            1000,
            rate,
            0,
            self.frames,
            self._max_size,
            0xFFFFFFFF,
            0,
            0,
            0,
            self.width,
            self.height,
        )

    def _strf(self) -> bytes:
        return struct.pack(
            "<IiiHH4sIiiII",
            40,
            self.width,
            self.height,
            1,
            24,
            b"MJPG",
            self.width * self.height * 3,
            0,
            0,
            0,
            0,
        )

    def _write_headers(self) -> None:
        strl = b"strl" + _chunk(b"strh", self._strh()) + _chunk(b"strf", self._strf())
        hdrl = b"hdrl" + _chunk(b"avih", self._avih()) + _chunk(b"LIST", strl)
        self._f.write(b"RIFF" + struct.pack("<I", self._PLACEHOLDER) + b"AVI ")
        self._f.write(_chunk(b"LIST", hdrl))
        self._avih_at = 12 + 8 + 4 + 8  # RIFF hdr, LIST hdr, 'hdrl', 'avih' hdr
        self._strh_at = self._avih_at + 56 + 8 + 4 + 8  # avih, LIST hdr, 'strl', 'strh' hdr
        self._movi_at = self._f.tell()  # the movi LIST header
        self._f.write(b"LIST" + struct.pack("<I", self._PLACEHOLDER) + b"movi")

    def write(self, image: np.ndarray) -> None:
        """image: (H, W, 3) uint8 BGR; raises OSError when the disk refuses it."""
        ok, jpeg = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, self.quality])
        if not ok:  # pragma: no cover - OpenCV encodes any uint8 image
            raise RecordingError(f"{self.path}: JPEG encoding failed")
        data = jpeg.tobytes()
        offset = self._f.tell() - (self._movi_at + 8)  # relative to the 'movi' fourcc
        try:
            self._f.write(_chunk(b"00dc", data))
        except OSError:
            self.failed = True
            raise
        self._index.append((offset, len(data)))
        self._max_size = max(self._max_size, len(data))
        self.frames += 1

    def close(self) -> None:
        """Write the index, fill in the sizes, flush and fsync. Safe to call twice.

        After a failed :meth:`write` the file is only released (the error was raised
        then; demuxers still read its whole frames by scanning the ``movi`` list).
        """
        if self._f.closed:
            return
        if self.failed:
            try:
                self._f.close()
            except OSError:
                pass  # the buffered tail of a file already known to be cut short
            return
        try:
            end_movi = self._f.tell()
            idx = b"".join(
                struct.pack("<4sIII", b"00dc", self._AVIIF_KEYFRAME, off, size)
                for off, size in self._index
            )
            self._f.write(_chunk(b"idx1", idx))
            end = self._f.tell()
            self._f.seek(4)
            self._f.write(struct.pack("<I", end - 8))
            self._f.seek(self._movi_at + 4)
            self._f.write(struct.pack("<I", end_movi - self._movi_at - 8))
            self._f.seek(self._avih_at)
            self._f.write(self._avih())
            self._f.seek(self._strh_at)
            self._f.write(self._strh())
            self._f.flush()
            os.fsync(self._f.fileno())
        finally:
            self._f.close()


def _chunk(fourcc: bytes, data: bytes) -> bytes:
    """A RIFF chunk: fourcc, little-endian size, data, padded to an even length."""
    pad = b"\0" if len(data) % 2 else b""
    return fourcc + struct.pack("<I", len(data)) + data + pad
