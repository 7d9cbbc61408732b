"""Headless cameras: a numpy rasteriser and GIF / MP4 recording (see camera.py)."""
from .camera import Camera  # noqa: F401
