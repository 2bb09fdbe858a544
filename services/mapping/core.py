"""The mapping service's core: frames, perception results and odometry in, map snapshots out.

No Zenoh and no bus here: the service adapter (:mod:`ovamos.services.mapping.service`) feeds
the core from its one thread and publishes what :meth:`MappingCore.poll` returns, so the
matching and session rules below are tested message by message.

Frames and perception results arrive on separate keys and are matched by
frame seq. A frame whose result has not come within ``match_timeout_s`` is
fused without values (obstacles, explored area, frontiers still grow), so a
slow or absent perception service never stalls the map. The value layers
follow the target list of the newest perception result. A frame counts once
(:class:`MapState`): the same frame again (re-published while the robot stands
still) is not fused again, and a second result for a fused frame (perception
re-scores its latest frame when targets are added) adds only the values of the
targets the frame was not fused for; the newest fused frames are kept for that.

One map per odometry session. The driver's current session changes only on the
evidence of a restart (:mod:`ovamos.shared.sessions`: a sustained stream of the new
session, on odometry or on frames, while the current one is quiet), so one
forged or replayed message cannot take the map away from the driver: it is
counted (``sessions.stray``) and ignored. A session once left is never followed
again (a session id is never used twice). A new session starts a fresh map: the map of the
earlier one is kept on disk beside the checkpoint under its session id
(:func:`~ovamos.services.mapping.checkpoint.session_path`) and never fused into again,
and frames and results of a session left behind are dropped and counted. The
checkpoint found at start is held until the current session is known and
resumed only when it is that session's (a mapping service restarted while the
driver runs); else it is kept under its session id, a session left behind.

One thread calls every method (fusing, snapshots for the periodic put and for queries,
checkpoints), so the map needs no lock and a snapshot is always of one consistent state
(:meth:`MapState.snapshot` copies). ``now`` arguments are ``time.monotonic()`` (the match
timeout, the checkpoint period); snapshot and checkpoint stamps are wall time.
"""

from __future__ import annotations

import logging
import time
from collections import Counter
from typing import Any

from ovamos.services.mapping.checkpoint import CheckpointError, load_checkpoint, save_checkpoint, session_path
from ovamos.services.mapping.config import MappingServiceConfig
from ovamos.services.mapping.state import MapState
from ovamos.shared.log import sampled
from ovamos.shared.messages import MapSnapshot, Odometry, PerceptionResult, RgbdFrame
from ovamos.shared.sessions import SessionFollower

__all__ = ["MappingCore"]


class MappingCore:
    """One robot's map, fed frames, results and odometry; see the module for the rules."""

    def __init__(self, config: MappingServiceConfig, log: logging.Logger, now: float) -> None:
        """``config.checkpoint_path`` is the file itself (see :meth:`MappingServiceConfig.for_robot`)."""
        self.config, self.log = config, log
        self._frames: dict[int, tuple[RgbdFrame, float]] = {}
        self._results: dict[int, PerceptionResult] = {}
        self._fused: dict[int, RgbdFrame] = {}  # the newest fused frames, for a second result
        self._changed = True
        self._last_checkpoint = now
        self._session: str | None = None   # the driver's current odometry session, once known
        self._held = self._load_checkpoint()  # resumed once the session is known to be its own
        self._sessions = SessionFollower(config.session_switch,
                                         None if self._held is None else self._held.odom_session)
        self.state = MapState(config)
        self.other_session: Counter[str] = Counter()  # frames / results of another session: dropped
        self.repeated = 0                    # frames that came again after they were fused

    def _load_checkpoint(self) -> MapState | None:
        path = self.config.checkpoint_path
        if path is not None and path.exists():
            try:
                return load_checkpoint(path, self.config)
            except CheckpointError as exc:
                self.log.error("%s; starting a fresh map", exc)
        return None

    # -- the odometry session --------------------------------------------------------------------
    def on_odom(self, odom: Odometry, now: float) -> None:
        """Odometry, received at ``now``: evidence of the driver's session (the frames carry their
        poses), and the base's own localization when it has one (kept for the map to follow)."""
        if self._admit("odom", odom.seq, odom.odom_session, now) and odom.map_T_odom is not None:
            localizer = self.state.localizer  # after _admit: a new session has a new map
            if localizer is not None:
                localizer.base = odom.map_T_odom

    def _admit(self, kind: str, seq: int, session: str, now: float) -> bool:
        """Whether odometry or a frame is of the current session, following a new one when the
        message completes the evidence of a restart; others are counted (and sampled in the log)."""
        if self._left_behind(kind, seq, session):
            return False
        if not self._sessions.admit(kind, session, seq, self.log):
            return False
        if self._sessions.current != self._session:
            evidence = self._sessions.switched_on
            if self._session is not None and evidence is not None:
                self.log.warning("the driver restarted: odometry session %r follows %r (%s of it)",
                                 evidence.session, self._session, evidence.describe())
            self._follow(session, now)
        return True

    def _follow(self, session: str, now: float) -> None:
        """Make ``session`` the current one, with its own map: the held checkpoint when it is that
        session's, else a fresh map (a map of another session is kept on disk, see the module)."""
        if session == self._session:
            return
        self._session, held, self._held = session, self._held, None
        self._frames = {s: p for s, p in self._frames.items() if p[0].odom_session == session}
        self._results = {s: r for s, r in self._results.items() if r.odom_session == session}
        if held is not None and held.odom_session == session:
            self.state, self._changed = held, True
            self.log.info("resumed the map from %s (odometry session %r, last frame seq %d)",
                          self.config.checkpoint_path, session, held.seq)
            return
        if held is not None:
            self._keep(held, "the checkpoint's map")
        if self.state.odom_session != session:
            if self.state.seq >= 0:
                self._keep(self.state, "the map")
            self.state, self._fused, self._changed = MapState(self.config, odom_session=session), {}, True
            self.log.info("odometry session %r: a fresh map", session)
        if self.config.checkpoint_path is not None:
            self._checkpoint(now)  # the checkpoint file is the current session's from now on

    def _keep(self, state: MapState, what: str) -> None:
        path = self.config.checkpoint_path
        if path is None:
            self.log.warning("%s of odometry session %r is dropped: the odometry session is now %r "
                             "(no checkpoint_path to keep it)", what, state.odom_session, self._session)
            return
        kept = session_path(path, state.odom_session)
        save_checkpoint(state, kept, time.time())
        self.log.warning("%s of odometry session %r is not fused into any more: the odometry session "
                         "is now %r; kept as %s", what, state.odom_session, self._session, kept)

    def _left_behind(self, kind: str, seq: int, session: str) -> bool:
        """Whether a message is of a session left behind (then it is counted)."""
        if session not in self._sessions.left:  # were current, or the held checkpoint's
            return False
        self.other_session[kind] += 1
        if kind != "odom" and sampled(self.other_session[kind]):
            self.log.warning("dropped %s %d of odometry session %r: the map is of session %r",
                             kind, seq, session, self._session)
        return True

    # -- frames and results ----------------------------------------------------------------------
    def on_frame(self, frame: RgbdFrame, now: float) -> None:
        """A camera frame, received at ``now``: fused with its result, or waiting for it."""
        if not self._admit("frame", frame.seq, frame.odom_session, now):
            return  # a new session's frames count as evidence: they may come before its odometry
        if self.state.has_fused(frame):
            self.repeated += 1  # re-published: its result, if one comes again, is matched below
            return
        result = self._results.pop(frame.seq, None)
        if result is None:
            self._frames.setdefault(frame.seq, (frame, now))  # a repeat keeps its wait
            _trim(self._frames, self.config.max_pending)
            return
        self._fuse(frame, result)

    def on_result(self, result: PerceptionResult) -> None:
        if self._left_behind("result", result.seq, result.odom_session):
            return
        pending = self._frames.pop(result.seq, None)
        fused = self._fused.get(result.seq)
        if pending is not None and pending[0].odom_session != result.odom_session:
            self._frames[result.seq] = pending  # of a newer session: its frame has yet to come
            pending = None
        if pending is not None:
            self._fuse(pending[0], result)
        elif fused is not None and fused.stamp == result.stamp and fused.odom_session == result.odom_session:
            self._fuse(fused, result)  # a second result (re-scored): new targets' values only
        else:
            self._results[result.seq] = result
            _trim(self._results, self.config.max_pending)

    def _fuse(self, frame: RgbdFrame, result: PerceptionResult | None) -> None:
        layers = self.state.layers
        fused = self.state.apply(frame, result)
        self._fused[frame.seq] = frame
        _trim(self._fused, self.config.max_pending)
        self._changed = self._changed or fused or self.state.layers != layers

    # -- periodic work -------------------------------------------------------------------------
    def poll(self, now: float) -> MapSnapshot | None:
        """Fuse the frames whose result did not come in time, checkpoint when due, and return
        the snapshot to publish when the map changed (None before the session is known)."""
        expired = sorted(s for s, (_, t) in self._frames.items() if now - t > self.config.match_timeout_s)
        for seq in expired:
            self._fuse(self._frames.pop(seq)[0], None)
        snapshot = None
        if self._changed and self._session is not None:
            snapshot, self._changed = self.snapshot(), False
        if self.config.checkpoint_path and now - self._last_checkpoint >= self.config.checkpoint_every_s:
            self._checkpoint(now)
        return snapshot

    def snapshot(self) -> MapSnapshot:
        """The map as the planner and the gateway see it (no fusion confidences)."""
        return self.state.snapshot(time.time(), with_confidence=False)

    def _checkpoint(self, now: float) -> None:
        self._save()
        self._last_checkpoint = now

    def _save(self) -> None:
        assert self.config.checkpoint_path is not None
        if self._session is not None:  # before, the file holds the checkpoint not yet resumed
            save_checkpoint(self.state, self.config.checkpoint_path, time.time())

    def close(self) -> None:
        """The last checkpoint, when the service stops."""
        if self.config.checkpoint_path:
            self._save()

    def info(self) -> dict[str, Any]:
        return {"seq": self.state.seq, "after_action": self.state.after_action,
                "odom_session": self.state.odom_session, "layers": list(self.state.layers),
                "explored_m2": round(float(self.state.explored.sum()) * self.config.resolution ** 2, 2),
                "objects": len(self.state.objects.instances()),
                "pending_frames": len(self._frames), "pending_results": len(self._results),
                "other_session_dropped": dict(self.other_session), "repeated_frames": self.repeated,
                "sessions": self._sessions.info(), **self._localization()}

    def _localization(self) -> dict[str, Any]:
        """The localizer's matches by verdict and where it has the odometry frame (absent without one)."""
        localizer = self.state.localizer
        if localizer is None:
            return {}
        t = localizer.map_T_odom
        return {"localization": {**localizer.counters, "map_T_odom": [round(t.x, 3), round(t.y, 3), round(t.yaw, 4)]}}


def _trim(pending: dict[int, Any], limit: int) -> None:
    """Drop the oldest (lowest seq) entries beyond ``limit``."""
    for seq in sorted(pending)[:max(0, len(pending) - limit)]:
        del pending[seq]
