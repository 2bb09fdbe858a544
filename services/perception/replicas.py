"""Sharing one frame stream between perception replicas without duplicated work.

Every replica holds a liveliness token ``ready/<robot>/perception/<instance>``
from the moment its backend is loaded and it takes frames, and watches the
others' tokens. Each sorts the live
instance names and takes the frames whose ``seq % n`` equals its own position:
no coordinator, no extra messages, and every frame has exactly one owner while
the replicas agree on the membership.

Membership changes: a replica that joins or leaves is seen by the others when
its token appears or disappears (at once on loopback and for a clean stop; a
killed or hung host is noticed after the Zenoh lease, ~3 s). Until every
replica has seen the change, their views differ, so a frame may be processed
twice (two results with the same seq: the map fuses the first, later ones
find no frame to pair with and are trimmed) or not at all (the map fuses that
frame without values after its match timeout). A replica that died mid-frame
loses that frame the same way. Nothing stalls and no state needs repair.

The ``ready`` token, not the bus's ``alive`` one, defines membership: ``alive``
is declared when the session opens, before the models load (seconds to a
minute for real weights), and counting a loading replica would lose its share
of the frames all that time. A stopping replica withdraws its ``ready`` token
first, before its session closes.

A :class:`ReplicaSet` is plain state: the core (:mod:`.core`) changes and reads it on the
service's one thread (membership changes arrive as inbox events like messages).
"""

from __future__ import annotations


class ReplicaSet:
    """The live perception instances as one replica sees them, and which frames it owns."""

    def __init__(self, me: str) -> None:
        self.me = me
        self._members = {me}

    def join(self, instance: str) -> None:
        self._members.add(instance)

    def leave(self, instance: str) -> None:
        """Forget ``instance``; this replica never forgets itself (its token may be re-declared)."""
        if instance != self.me:
            self._members.discard(instance)

    def members(self) -> list[str]:
        return sorted(self._members)

    def owns(self, seq: int) -> bool:
        members = self.members()
        return seq % len(members) == members.index(self.me)
