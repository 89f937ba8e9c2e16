"""Write a sequence of frames (Pillow images) as an animated GIF or an MP4 video.

GIF is always available (Pillow). Every frame is mapped onto one fixed palette without dithering,
so the colours drawn from the palette (the roles, the road) stay exact in the file, and a viewer
(or a test) finds the ego's red where it was drawn. GIF frames are kept in memory until the file
is written (Pillow's writer needs them all), about 0.45 MB per 640 x 704 frame, hence
:data:`MAX_GIF_FRAMES`.

MP4 (H.264) needs an ffmpeg binary: ``imageio-ffmpeg`` ships one in its wheel (a requirement of
der_ros), or ``IMAGEIO_FFMPEG_EXE`` names one. Frames are streamed to it, so a video of many
episodes needs no more memory than one frame. Without an encoder, :class:`EncoderUnavailable`
says so and suggests a GIF.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any

from PIL import Image

__all__ = ["EncoderUnavailable", "AnimationError", "FORMATS", "MAX_GIF_FRAMES", "mp4_encoder", "palette_image",
           "check_output", "write_animation"]  # fmt: skip

#: file suffixes the writer knows
FORMATS = (".gif", ".mp4")
#: more frames than this in one GIF would hold gigabytes while writing: use fewer episodes or MP4
MAX_GIF_FRAMES = 3000


class AnimationError(ValueError):
    """A bad output request (unknown suffix, too many frames); ``der`` prints it as one line."""

    user_facing = True


class EncoderUnavailable(RuntimeError):
    """No MP4 encoder is installed."""

    user_facing = True


def mp4_encoder() -> str:
    """The ffmpeg executable ``imageio-ffmpeg`` provides; :class:`EncoderUnavailable` if none."""
    try:
        import imageio_ffmpeg  # optional at run time: GIFs do not need it
    except ImportError:
        raise EncoderUnavailable(
            "cannot write MP4: no video encoder (the imageio-ffmpeg package, which ships ffmpeg, is not installed); "
            "install it (pip install imageio-ffmpeg) or write a GIF instead: --to out.gif"
        ) from None
    try:
        return str(imageio_ffmpeg.get_ffmpeg_exe())
    except RuntimeError as exc:
        raise EncoderUnavailable(f"cannot write MP4: no ffmpeg binary found ({exc}); write a GIF instead: --to out.gif") from None


def palette_image(colours: Sequence[tuple[int, int, int]]) -> Image.Image:
    """A "P" image whose palette is ``colours`` (at most 256), for :meth:`PIL.Image.Image.quantize`."""
    if not 0 < len(colours) <= 256:
        raise ValueError(f"{len(colours)} palette colours, expected 1..256")
    flat = [c for rgb in colours for c in rgb]
    pal = Image.new("P", (1, 1))
    pal.putpalette(flat + flat[-3:] * (256 - len(colours)))
    return pal


def check_output(path: str | Path) -> Path:
    """``path`` if its suffix is a known format (checked before any work), else :class:`AnimationError`."""
    path = Path(path)
    if path.suffix.lower() not in FORMATS:
        raise AnimationError(f"--to {path}: unknown animation format {path.suffix!r}, expected one of {FORMATS}")
    if path.suffix.lower() == ".mp4":
        mp4_encoder()
    return path


def write_animation(frames: Iterable[Image.Image], path: str | Path, fps: float,
                    palette: Sequence[tuple[int, int, int]] | None = None) -> int:  # fmt: skip
    """Write ``frames`` (RGB, all one size) to ``path`` (.gif or .mp4) at ``fps`` frames per second;
    returns the number of frames written. ``palette``: the GIF's colours (else Pillow's adaptive one)."""
    path = check_output(path)
    suffix = path.suffix.lower()
    if not fps > 0:
        raise AnimationError(f"fps = {fps!r}, expected > 0")
    path.parent.mkdir(parents=True, exist_ok=True)
    if suffix == ".mp4":
        return _write_mp4(frames, path, fps)
    return _write_gif(frames, path, fps, palette)


def _write_gif(frames: Iterable[Image.Image], path: Path, fps: float,
               palette: Sequence[tuple[int, int, int]] | None) -> int:  # fmt: skip
    pal = palette_image(palette) if palette is not None else None
    images: list[Image.Image] = []
    for frame in frames:
        if len(images) >= MAX_GIF_FRAMES:
            raise AnimationError(f"more than {MAX_GIF_FRAMES} frames for one GIF; choose fewer episodes or write .mp4")
        rgb = frame.convert("RGB")
        images.append(rgb.quantize(palette=pal, dither=Image.Dither.NONE) if pal is not None else rgb.quantize())
    if not images:
        raise AnimationError(f"no frames to write to {path}")
    # GIF delays are in hundredths of a second
    duration = max(20, int(round(1000.0 / fps / 10.0)) * 10)
    images[0].save(path, save_all=True, append_images=images[1:], duration=duration, loop=0, optimize=False)
    return len(images)


def _write_mp4(frames: Iterable[Image.Image], path: Path, fps: float) -> int:
    mp4_encoder()  # a clear error before any work when there is none
    import imageio_ffmpeg  # optional at run time (see mp4_encoder)

    writer: Any = None
    n = 0
    try:
        for frame in frames:
            rgb = frame.convert("RGB")
            if writer is None:
                writer = imageio_ffmpeg.write_frames(str(path), rgb.size, fps=fps, codec="libx264",
                                                     pix_fmt_out="yuv420p", macro_block_size=16,
                                                     ffmpeg_log_level="error")  # fmt: skip
                writer.send(None)  # start ffmpeg
            writer.send(rgb.tobytes())
            n += 1
    finally:
        if writer is not None:
            writer.close()
    if n == 0:
        raise AnimationError(f"no frames to write to {path}")
    return n
