"""Writing and reading videos with PyAV, keeping each frame's presentation time: the videos a user
tracks, the overlay videos, and the synthetic clips.

A leaf module: it imports nothing from surftrack, so that :mod:`surftrack.synth.clip`, an earlier stage,
can write its clips with it (the one exception to the stage order; see :mod:`surftrack.io`).

:class:`VideoWriter` encodes uint8 RGB frames to H.264 in MP4 (by default) with a timestamp per frame:
the one given to :meth:`VideoWriter.write`, so variable frame rates survive, else ``i / fps``.
Timestamps are kept at 1/90000 s. The encoder uses a short GOP and no B-frames, which keeps decoders
(and Foxglove) simple. The writer is a context manager that closes the file even when the ``with``
block raises, so an interrupted clip is still a valid, decodable MP4 of the frames written so far.

:func:`read_video_frames` yields ``(time_s, frame)`` with the time taken from each frame's
presentation timestamp relative to the stream start, never from its index and a nominal frame rate.
"""

from __future__ import annotations

from collections.abc import Iterator
from fractions import Fraction
from pathlib import Path

import av
import numpy as np

TIME_BASE = Fraction(1, 90000)
_CRF_CODECS = {"libx264", "libx265", "libvpx-vp9", "libaom-av1", "libsvtav1"}


def _subsampling(pix_fmt: str) -> tuple[int, int]:
    """Horizontal and vertical chroma subsampling factors of a pixel format (1 = none)."""
    if "420" in pix_fmt or pix_fmt in ("nv12", "nv21"):
        return 2, 2
    if "422" in pix_fmt or "411" in pix_fmt:
        return (4 if "411" in pix_fmt else 2), 1
    return 1, 1


class VideoWriter:
    """Encodes uint8 RGB frames (height, width, 3) to a video file with per-frame timestamps.

    ``fps`` is the nominal rate: it sets the timestamps of frames written without one and is a hint to
    the encoder's rate control. ``crf`` is the constant-rate-factor quality (lower is better; used by
    x264/x265/VPx/AV1 encoders). Use as a context manager, or call :meth:`close`.
    """

    def __init__(self, path: str | Path, fps: float, width: int, height: int, codec: str = "libx264",
                 crf: int = 18, pix_fmt: str = "yuv420p", gop: int = 30) -> None:
        self.path = Path(path)
        if not fps > 0:
            raise ValueError(f"{self.path}: fps must be positive, got {fps}")
        if width <= 0 or height <= 0:
            raise ValueError(f"{self.path}: frame size must be positive, got {width}x{height}")
        sx, sy = _subsampling(pix_fmt)
        if width % sx or height % sy:
            need = "an even width and height" if (sx, sy) == (2, 2) else f"width % {sx} == 0 and height % {sy} == 0"
            raise ValueError(f"{self.path}: {pix_fmt} needs {need}, got {width}x{height} (crop or pad the frames)")
        self.fps, self.width, self.height, self.pix_fmt = float(fps), int(width), int(height), pix_fmt
        self.frames_written = 0
        self._last_pts: int | None = None
        self._container = av.open(str(self.path), mode="w")
        try:
            rate = Fraction(self.fps).limit_denominator(1001000)
            options = {"g": str(int(gop)), "bf": "0"}
            if codec in _CRF_CODECS:
                options["crf"] = str(int(crf))
            stream = self._container.add_stream(codec, rate=rate, options=options)
            stream.width, stream.height, stream.pix_fmt = self.width, self.height, pix_fmt
            stream.time_base = TIME_BASE
            stream.codec_context.time_base = TIME_BASE
        except Exception:
            self._container.close()
            raise
        self._stream = stream

    @property
    def closed(self) -> bool:
        return self._container is None

    def write(self, rgb: np.ndarray, pts_seconds: float | None = None) -> None:
        """Encode one frame shown at ``pts_seconds`` (default ``frame_index / fps``); times must increase."""
        if self._container is None:
            raise ValueError(f"{self.path}: write() on a closed VideoWriter")
        rgb = np.asarray(rgb)
        if rgb.dtype != np.uint8 or rgb.shape != (self.height, self.width, 3):
            raise ValueError(f"{self.path}: expected a uint8 RGB frame of shape {(self.height, self.width, 3)}, "
                             f"got {rgb.dtype} {rgb.shape}")
        t = self.frames_written / self.fps if pts_seconds is None else float(pts_seconds)
        if not 0.0 <= t < float("inf"):
            raise ValueError(f"{self.path}: frame time must be finite and >= 0 s, got {t}")
        pts = int(round(t / TIME_BASE))
        if self._last_pts is not None and pts <= self._last_pts:
            raise ValueError(f"{self.path}: frame time {t:.6f} s does not increase "
                             f"(previous frame at {float(self._last_pts * TIME_BASE):.6f} s)")
        frame = av.VideoFrame.from_ndarray(np.ascontiguousarray(rgb), format="rgb24").reformat(format=self.pix_fmt)
        frame.pts = pts
        frame.time_base = TIME_BASE
        for packet in self._stream.encode(frame):
            self._container.mux(packet)
        self._last_pts = pts
        self.frames_written += 1

    def close(self) -> None:
        """Flush the encoder and close the file (idempotent). A writer given no frames writes no file."""
        if self._container is None:
            return
        container, self._container = self._container, None
        try:
            for packet in self._stream.encode(None):
                container.mux(packet)
        finally:
            container.close()

    def __enter__(self) -> VideoWriter:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        self.close()


def _one_line(e: BaseException) -> str:
    text = str(e).strip().splitlines()
    return f"{type(e).__name__}: {text[0] if text else ''}".rstrip(": ")


def read_video_frames(path: str | Path, as_gray: bool = False) -> Iterator[tuple[float, np.ndarray]]:
    """Iterate ``(time_s, frame)`` over the first video stream of ``path``.

    ``frame`` is uint8 RGB (H, W, 3), or (H, W) luma with ``as_gray``. ``time_s`` is
    ``(pts - stream.start_time) * time_base`` (start_time 0 when unknown). The file is opened here, so a
    missing or unreadable file, or one without a video stream, raises ``ValueError`` naming ``path`` at
    the call, not at the first iteration.
    """
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"{path}: no such video file")
    try:
        container = av.open(str(path), mode="r")
    except (av.FFmpegError, OSError) as e:
        raise ValueError(f"{path}: cannot open as a video ({_one_line(e)})") from e
    if not container.streams.video:
        container.close()
        raise ValueError(f"{path}: has no video stream")
    return _frames(container, container.streams.video[0], path, as_gray)


def _frames(container, stream, path: Path, as_gray: bool) -> Iterator[tuple[float, np.ndarray]]:
    fmt = "gray" if as_gray else "rgb24"
    start = stream.start_time or 0
    try:
        for frame in container.decode(stream):
            if frame.pts is None:
                raise ValueError(f"{path}: a decoded frame has no presentation timestamp")
            time_base = frame.time_base or stream.time_base
            yield float((frame.pts - start) * time_base), frame.to_ndarray(format=fmt)
    except av.FFmpegError as e:
        raise ValueError(f"{path}: decoding failed ({_one_line(e)})") from e
    finally:
        container.close()
