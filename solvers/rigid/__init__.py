"""Rigid articulated solver: generalised-coordinate dynamics in Taichi kernels."""
from .model import EntityModel, LinkDesc, GeomDesc, MimicDesc  # noqa: F401
