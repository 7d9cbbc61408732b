"""Frame spooling and GIF / MP4 writers (Pillow; imageio-ffmpeg, whose pip wheel carries its own
ffmpeg binary, so nothing outside pip is needed)."""
from __future__ import annotations

import os
import tempfile

import numpy as np

from ..errors import GenesisException

SUPPORTED = (".gif", ".mp4")


class FrameSpool:
    """Frames of one recording, kept in an anonymous temporary file rather than in memory: a few
    hundred 640x480 frames are hundreds of MB, and the output file (hence the frame rate and the
    format) is only known when the recording stops."""

    def __init__(self):
        self._file = tempfile.TemporaryFile()
        self.shape = None
        self.n = 0

    def append(self, rgb: np.ndarray):
        rgb = np.ascontiguousarray(rgb, dtype=np.uint8)
        if self.shape is None:
            self.shape = rgb.shape
        elif rgb.shape != self.shape:
            raise GenesisException(f"camera recording: frame of shape {rgb.shape} after frames of shape {self.shape}; "
                                   "a recording keeps one resolution")
        self._file.write(rgb.tobytes())
        self.n += 1

    def __iter__(self):
        size = int(np.prod(self.shape))
        self._file.seek(0)
        for _ in range(self.n):
            yield np.frombuffer(self._file.read(size), dtype=np.uint8).reshape(self.shape)
        self._file.seek(0, os.SEEK_END)

    def close(self):
        self._file.close()


def check_output_path(path) -> str:
    """Validate an output video path and create its folder; returns it as an absolute path.
    Raises GenesisException naming the path for an unsupported extension or a folder that cannot be
    created or written."""
    try:
        path = os.path.abspath(os.fspath(path))
    except TypeError:
        raise GenesisException(f"save_to_filename={path!r}: expected a file path ending in .gif or .mp4") from None
    ext = os.path.splitext(path)[1].lower()
    if ext not in SUPPORTED:
        raise GenesisException(f"cannot write video '{path}': unsupported extension '{ext or '(none)'}'; "
                               "the supported formats are .gif and .mp4")
    if os.path.isdir(path):
        raise GenesisException(f"cannot write video '{path}': it is an existing folder; "
                               f"give a file name ending in {ext}")
    folder = os.path.dirname(path)
    try:
        os.makedirs(folder, exist_ok=True)
    except OSError as e:
        raise GenesisException(f"cannot write video '{path}': its folder '{folder}' cannot be created "
                               f"({e.strerror or e}); choose a path in a writable folder") from e
    if not os.access(folder, os.W_OK):
        raise GenesisException(f"cannot write video '{path}': folder '{folder}' is not writable; "
                               "choose a path in a writable folder")
    return path


def _even(frame):
    """yuv420p needs even width and height: repeat the last row / column when one is odd."""
    h, w = frame.shape[:2]
    if h % 2 or w % 2:
        frame = np.pad(frame, ((0, h % 2), (0, w % 2), (0, 0)), mode="edge")
    return frame


def _write_mp4(frames, shape, path, fps):
    import imageio_ffmpeg

    h, w = shape[0] + shape[0] % 2, shape[1] + shape[1] % 2
    gen = imageio_ffmpeg.write_frames(path, (w, h), fps=float(fps), codec="libx264", pix_fmt_in="rgb24",
                                      pix_fmt_out="yuv420p", quality=8, macro_block_size=1, ffmpeg_log_level="error")
    gen.send(None)
    try:
        for f in frames:
            gen.send(np.ascontiguousarray(_even(f)))
    finally:
        gen.close()


def _write_gif(frames, path, fps):
    from PIL import Image

    def images():
        for f in frames:
            # one adaptive palette per frame; no dithering, whose noise would change every frame
            yield Image.fromarray(f).quantize(colors=256, method=Image.Quantize.FASTOCTREE, dither=Image.Dither.NONE)

    it = images()
    first = next(it)
    # GIF delays are whole hundredths of a second
    duration = max(10, int(round(100.0 / fps)) * 10)
    first.save(path, format="GIF", save_all=True, append_images=it, duration=duration, loop=0, optimize=False)


def write_video(spool: FrameSpool, path: str, fps: float):
    """Encode the spooled frames into `path` (.gif or .mp4 from its extension) at `fps` frames per
    second. The file appears only once complete (written under a temporary name, then renamed)."""
    ext = os.path.splitext(path)[1].lower()
    folder, base = os.path.split(path)
    tmp = os.path.join(folder, f".{base}.{os.getpid()}.partial{ext}")
    try:
        if ext == ".mp4":
            _write_mp4(iter(spool), spool.shape, tmp, fps)
        else:
            _write_gif(iter(spool), tmp, fps)
        os.replace(tmp, path)
    except (OSError, RuntimeError) as e:
        raise GenesisException(f"cannot write video '{path}': {type(e).__name__}: {e}") from e
    finally:
        if os.path.exists(tmp):
            os.remove(tmp)
