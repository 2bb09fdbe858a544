"""Sharing one frame stream between perception replicas without duplicated work.

Every replica holds a liveliness token ``alive/<robot>/perception/<instance>``
(the bus declares it) and watches the others' tokens. Each sorts the live
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

One known gap: the bus declares a replica's token when its session opens,
before its backend has loaded, so a starting replica's share of the frames is
lost while its models load (seconds for real weights). A separate "ready"
token, declared once :meth:`Service.start` returns, would close it.
"""

from __future__ import annotations

import threading


class ReplicaSet:
    """The live perception instances as one replica sees them, and which frames it owns."""

    def __init__(self, me: str) -> None:
        self.me = me
        self._lock = threading.Lock()
        self._members = {me}

    def join(self, instance: str) -> None:
        with self._lock:
            self._members.add(instance)

    def leave(self, instance: str) -> None:
        """Forget ``instance``; this replica never forgets itself (its token may be re-declared)."""
        if instance != self.me:
            with self._lock:
                self._members.discard(instance)

    def members(self) -> list[str]:
        with self._lock:
            return sorted(self._members)

    def owns(self, seq: int) -> bool:
        members = self.members()
        return seq % len(members) == members.index(self.me)
