"""Frames to video files: captions, tiles side by side, GIF (Pillow) and MP4 (imageio-ffmpeg), written atomically.

Pillow is there with matplotlib; captions use its default font (a scalable
one when Pillow has FreeType, else its small bitmap font). MP4 needs the
ffmpeg binary that imageio-ffmpeg ships; without it, asking for an MP4 is
one clear error before any frame is rendered.
"""

from __future__ import annotations

import math
import tempfile
from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw, ImageFont

from morph_core.util.atomic import atomic_write_bytes, atomic_writer

GAP_COLOR = (255, 255, 255)
_CAPTION_BG = (0, 0, 0, 170)


class VideoError(RuntimeError):
    """A video that cannot be written; ``str(err)`` is one line."""


def caption_font(height: int) -> ImageFont.ImageFont:
    """A font whose text is about ``height`` pixels tall."""
    try:
        return ImageFont.load_default(size=height)
    except (TypeError, ImportError, OSError):  # Pillow without FreeType: its fixed bitmap font
        return ImageFont.load_default()


def add_caption(frame: np.ndarray, text: str, font: ImageFont.ImageFont) -> np.ndarray:
    """``frame`` (uint8 [H, W, 3]) with ``text`` on a dark strip across its top left."""
    image = Image.fromarray(frame).convert("RGBA")
    overlay = Image.new("RGBA", image.size, (0, 0, 0, 0))
    draw = ImageDraw.Draw(overlay)
    left, top, right, bottom = draw.textbbox((0, 0), text, font=font)
    pad = max(2, (bottom - top) // 4)
    draw.rectangle((0, 0, right - left + 2 * pad, bottom - top + 2 * pad), fill=_CAPTION_BG)
    draw.text((pad - left, pad - top), text, font=font, fill=(255, 255, 255, 255))
    return np.asarray(Image.alpha_composite(image, overlay).convert("RGB"))


def tile(frames: list[np.ndarray], columns: int, gap: int = 2) -> np.ndarray:
    """Equal-sized frames in a grid, row by row, ``gap`` pixels of ``GAP_COLOR`` between them;
    a last row that is short is filled with the gap colour."""
    if not frames:
        raise ValueError("no frames to tile")
    h, w, _ = frames[0].shape
    if any(f.shape != frames[0].shape for f in frames):
        raise ValueError("frames to tile must all have one size")
    columns = max(1, min(columns, len(frames)))
    rows = math.ceil(len(frames) / columns)
    out = np.empty((rows * h + (rows - 1) * gap, columns * w + (columns - 1) * gap, 3), dtype=np.uint8)
    out[:] = GAP_COLOR
    for i, f in enumerate(frames):
        r, c = divmod(i, columns)
        out[r * (h + gap) : r * (h + gap) + h, c * (w + gap) : c * (w + gap) + w] = f
    return out


def ffmpeg_exe() -> str:
    """Path of imageio-ffmpeg's ffmpeg; VideoError when it is not installed."""
    try:
        # the ffmpeg binary's package only when a video is written
        import imageio_ffmpeg

        return imageio_ffmpeg.get_ffmpeg_exe()
    except (ImportError, RuntimeError) as err:
        raise VideoError(f"MP4 needs imageio-ffmpeg (pip install imageio-ffmpeg): {err}") from None


class VideoWriter:
    """Frames in one at a time; ``close()`` writes the GIF and/or MP4, each atomically (a reader sees
        no file or a whole one). Frames must all have one size; MP4 frames are padded to even sides
        (H.264 in yuv420p needs them). GIF frames are kept as palette images (``gif_colors``
    each) until ``close()``; Pillow stores a frame equal to the one before as a longer delay."""

    def __init__(self, fps: float, gif: Path | None = None, mp4: Path | None = None, gif_colors: int = 256):
        if gif is None and mp4 is None:
            raise ValueError("give a GIF path, an MP4 path or both")
        if not (fps > 0 and math.isfinite(fps)):
            raise ValueError(f"fps must be > 0, got {fps}")
        if not 2 <= gif_colors <= 256:
            raise ValueError(f"gif_colors must be in 2..256, got {gif_colors}")
        self.fps = fps
        self.gif_colors = gif_colors
        self.gif, self.mp4 = gif, mp4
        self.frames = 0
        self._gif_frames: list[Image.Image] = []
        self._size: tuple[int, int] | None = None
        self._tmp: tempfile.TemporaryDirectory | None = None
        self._mp4_pipe = None
        if mp4 is not None:
            self._exe = ffmpeg_exe()

    def add(self, frame: np.ndarray) -> None:
        frame = np.ascontiguousarray(frame, dtype=np.uint8)
        if self._size is None:
            self._size = frame.shape[:2]
            if self.mp4 is not None:
                self._start_mp4()
        elif frame.shape[:2] != self._size:
            raise ValueError(f"frame of {frame.shape[:2]} after frames of {self._size}")
        if self.gif is not None:
            self._gif_frames.append(
                Image.fromarray(frame).quantize(colors=self.gif_colors, method=Image.Quantize.MEDIANCUT)
            )
        if self._mp4_pipe is not None:
            h, w = self._size
            padded = np.empty((h + h % 2, w + w % 2, 3), dtype=np.uint8)
            padded[:] = GAP_COLOR
            padded[:h, :w] = frame
            self._mp4_pipe.send(padded.tobytes())
        self.frames += 1

    def _start_mp4(self) -> None:
        # the ffmpeg binary's package only when a video is written
        import imageio_ffmpeg

        self._tmp = tempfile.TemporaryDirectory(prefix="morph-render-")
        h, w = self._size
        self._mp4_pipe = imageio_ffmpeg.write_frames(
            str(Path(self._tmp.name) / "video.mp4"),
            (w + w % 2, h + h % 2),
            fps=self.fps,
            codec="libx264",
            pix_fmt_out="yuv420p",
            macro_block_size=1,
            quality=7,
            ffmpeg_log_level="error",
        )
        self._mp4_pipe.send(None)  # start the generator

    def close(self) -> list[Path]:
        """Write the files; returns their paths."""
        if self.frames == 0:
            raise ValueError("no frames were added")
        written = []
        if self.gif is not None:
            first, *rest = self._gif_frames
            with atomic_writer(self.gif, "wb") as f:
                # GIF delays are whole centiseconds: the nearest one (Pillow would truncate 119.99 ms to 110)
                delay_ms = 10 * max(1, round(100 / self.fps))
                first.save(f, format="GIF", save_all=True, append_images=rest, duration=delay_ms, loop=0)
            self._gif_frames = []
            written.append(self.gif)
        if self._mp4_pipe is not None:
            self._mp4_pipe.close()
            atomic_write_bytes(self.mp4, (Path(self._tmp.name) / "video.mp4").read_bytes())
            self._tmp.cleanup()
            self._mp4_pipe = None
            written.append(self.mp4)
        return written

    def abort(self) -> None:
        """Stop without writing anything (the temporary MP4 is removed)."""
        if self._mp4_pipe is not None:
            self._mp4_pipe.close()
            self._mp4_pipe = None
        if self._tmp is not None:
            self._tmp.cleanup()
        self._gif_frames = []
