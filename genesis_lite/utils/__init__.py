"""Genesis's `gs.utils` helpers that its scripts call (`gs.utils.geom`, `gs.tools`, `gs.UID`)."""
from . import geom, tools  # noqa: F401
from .uid import UID  # noqa: F401
