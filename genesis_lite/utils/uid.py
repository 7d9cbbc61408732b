"""Genesis's `gs.UID`: the id an entity gets when it is added to a scene."""
from __future__ import annotations

import uuid


class UID:
    """A random id of 32 hex digits (a version-4 UUID), as Genesis gives each entity. `str(uid)` is the 32
    digits, `uid.short()` their first 7 (what Genesis prints in its logs and what `scene.get_entity(uid=)`
    takes), `uid.full()` the digits with a dash after the 7th, and an f-string shows `<short>`. Two UIDs
    are equal when their digits are; an entity's index in its scene is `entity.idx`, not its uid."""

    __slots__ = ("uid",)

    def __init__(self) -> None:
        self.uid = uuid.uuid4().hex

    @classmethod
    def unique(cls, taken) -> "UID":
        """A new UID whose short form is none of `taken` (the short forms already used in a scene), so
        that the short form names one entity of the scene."""
        uid = cls()
        while uid.short() in taken:
            uid = cls()
        return uid

    def short(self) -> str:
        return self.uid[:7]

    def full(self) -> str:
        return f"{self.uid[:7]}-{self.uid[7:]}"

    def match(self, other: str, short_only: bool = False) -> bool:
        """Whether `other` (a string) is this UID: its 32 digits, or with short_only=True its short form."""
        return (self.short() if short_only else self.uid) == other

    def __str__(self) -> str:
        return self.uid

    def __repr__(self) -> str:
        return f"UID('{self.full()}')"

    def __format__(self, spec) -> str:
        return f"<{self.short()}>"

    def __eq__(self, other) -> bool:
        return isinstance(other, UID) and other.uid == self.uid

    def __hash__(self) -> int:
        return hash(self.uid)
