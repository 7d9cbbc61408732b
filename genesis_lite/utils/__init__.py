"""Genesis's `gs.utils` helpers that its scripts call (`gs.utils.geom`)."""
from . import geom  # noqa: F401
