"""A snapshot is one consistent state of the map, however long its encoding takes.

The mapping service encodes snapshots (for the periodic put and for queries)
while frames keep being fused; a snapshot that shared the live grids would
mix the counts of one frame with the values and seq of another.
"""

from __future__ import annotations

import threading

from ovamos.services.mapping.config import MappingConfig
from ovamos.services.mapping.state import MapState
from ovamos.shared.messages import MapSnapshot, PerceptionResult
from ovamos.world.render import SceneRenderer
from tests.sim_scenes import two_rooms

FRAMES = 40


def _frames() -> list:
    renderer = SceneRenderer(two_rooms(), 160, 120)
    try:
        frame = renderer.render(1.5, 2.0, 0.0)
    finally:
        renderer.close()
    return [frame.model_copy(update={"seq": i, "after_action": i}) for i in range(FRAMES)]


def _result(seq: int, shape: tuple[int, int]) -> PerceptionResult:
    return PerceptionResult.build(seq, 0.0, {"cup": 0.2 + 0.6 * (seq % 2)}, [], shape)


def test_snapshots_encoded_while_frames_are_fused_are_never_torn() -> None:
    frames = _frames()
    shape = frames[0].depth.shape
    # what each seq's snapshot must hold, from fusing the same frames one after the other
    reference = MapState(MappingConfig(), targets=("cup",))
    expected: dict[int, tuple[int, float]] = {}
    for frame in frames:
        reference.apply(frame, _result(frame.seq, shape))
        expected[frame.seq] = (int(reference.counts["cup"].max()), float(reference.values["cup"].sum()))

    state = MapState(MappingConfig(), targets=("cup",))
    lock = threading.Lock()  # the service's one thread, as two threads taking turns
    done = threading.Event()

    def fuse() -> None:
        for frame in frames:
            with lock:
                state.apply(frame, _result(frame.seq, shape))
        done.set()

    writer = threading.Thread(target=fuse)
    writer.start()
    seen = 0
    while not done.is_set() or seen == 0:
        with lock:
            snapshot = state.snapshot(0.0, with_confidence=False)
        # encoded outside the lock, while the writer goes on fusing
        decoded = MapSnapshot.from_bytes(snapshot.to_bytes())
        if decoded.seq < 0:
            continue
        seen += 1
        counts, value_sum = expected[decoded.seq]
        assert decoded.after_action == decoded.seq
        assert int(decoded.counts.max()) == counts, f"counts of another frame than seq {decoded.seq}"
        assert float(decoded.values[0].sum()) == value_sum, f"values of another frame than {decoded.seq}"
    writer.join()
    assert seen >= 1
