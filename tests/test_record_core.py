"""The recorder's and replay's cores without Zenoh: bounded queue, split files, pacing, channel metadata."""

from __future__ import annotations

from pathlib import Path

import foxglove
import pytest
from mcap.reader import make_reader

from ovamos.record.channels import META_VERSION, RawChannel, UnknownKeyError, from_metadata, select
from ovamos.record.recorder import Recorder, RecorderConfig, RecordingExistsError, part_path
from ovamos.record.replay import RawMessage, ReadReport, paced, read_raw
from ovamos.shared.messages import Odometry, TaskSpec
from tests.polling import wait_for

pytestmark = pytest.mark.serial  # real-time devices, rates or deadlines: run alone, after the parallel tests (make test-all)


def _odom(seq: int) -> bytes:
    return Odometry(seq=seq, stamp=0.0, x=seq * 0.1, y=0.0, yaw=0.0).to_bytes()


def test_a_payload_beyond_the_budget_is_dropped_and_counted_and_so_is_an_unknown_key(tmp_path: Path) -> None:
    rec = Recorder(tmp_path / "r.mcap", select(["odom"]), "r1", RecorderConfig(budget_bytes=1000, views=False))
    try:
        assert rec.offer("odom", _odom(1))
        assert not rec.offer("odom", b"x" * 1001)      # would never fit: memory stays bounded
        assert not rec.offer("rgbd", b"frame")          # not a recorded key
    finally:
        rec.close()
    stats = rec.stats()
    assert stats["written"] == {"odom": 1} and stats["dropped"] == {"odom": 1, "rgbd": 1}
    assert not rec.offer("odom", _odom(2))             # closed
    with pytest.raises(RecordingExistsError):
        Recorder(tmp_path / "r.mcap", select(["odom"]), "r1")


def test_split_files_each_close_with_an_index_and_hold_every_message_once(tmp_path: Path) -> None:
    path = tmp_path / "run.mcap"
    config = RecorderConfig(split_bytes=10_000, flush_s=0.05, compression="none", views=False)
    rec = Recorder(path, select(["task_current"]), "r1", config)
    sent = []
    for i in range(12):  # ~4 kB each: the targets are long names
        spec = TaskSpec(task_id=f"t{i}", targets=tuple(f"{i}-{'x' * 240}-{k}" for k in range(16)), stamp=float(i))
        sent.append(bytes(spec.to_bytes()))
        before = (len(rec.files), rec.files[-1].stat().st_size)
        assert rec.offer("task_current", sent[-1])
        # past a flush (the file grew, or a new part began): the size check has seen this message
        wait_for(lambda: (len(rec.files), rec.files[-1].stat().st_size) != before, 10, f"message {i} flushed")
    rec.close()
    assert len(rec.files) >= 3 and rec.files[1] == part_path(path, 1) == tmp_path / "run.1.mcap"
    got = []
    for part in rec.files:
        with part.open("rb") as f:
            reader = make_reader(f)
            assert reader.get_summary() is not None
            got += [m.data for _, _, m in reader.iter_messages()]
    assert got == sent


def test_pacing_keeps_the_recorded_gaps_scaled_by_the_rate() -> None:
    now = [0.0]
    slept = []

    def sleep(s: float) -> None:
        slept.append(s)
        now[0] += s

    channel = RawChannel("odom", Odometry, "r1")
    msgs = [RawMessage(channel, _odom(i), t) for i, t in enumerate((10**9, 2 * 10**9, 4 * 10**9))]
    times = [now[0] for _ in paced(iter(msgs), 2.0, clock=lambda: now[0], sleep=sleep)]
    assert times == pytest.approx([0.0, 0.5, 1.5])
    slept.clear()
    assert len(list(paced(iter(msgs), None, clock=lambda: now[0], sleep=sleep))) == 3 and not slept


def test_channels_of_other_versions_or_unknown_keys_are_skipped_and_listed(tmp_path: Path) -> None:
    good = RawChannel("odom", Odometry, "r1")
    with pytest.raises(UnknownKeyError, match="v99"):
        from_metadata({**good.metadata(), META_VERSION: "99"})
    with pytest.raises(UnknownKeyError, match="known: "):
        select(["odom", "no_such_key"])
    path = tmp_path / "mixed.mcap"
    context = foxglove.Context()
    writer = foxglove.open_mcap(path, context=context)
    good.open(context).log(_odom(1), log_time=1)
    future = foxglove.Channel("ovamos/r1/future", context=context, message_encoding="json",
                              metadata={**good.metadata(), "ovamos.key": "future"})
    future.log(b"{}", log_time=2)
    writer.close()
    report = ReadReport()
    assert [m.payload for m in read_raw(path, None, report)] == [_odom(1)]
    assert report.read == {"odom": 1} and len(report.skipped_channels) == 1
    assert "future" in report.skipped_channels[0]


def test_a_writer_that_cannot_go_on_stops_taking_and_says_why(tmp_path: Path) -> None:
    path = tmp_path / "run.mcap"
    part_path(path, 1).mkdir()  # the second part cannot be created
    config = RecorderConfig(split_bytes=1, flush_s=0.05, views=False, overwrite=True)
    rec = Recorder(path, select(["odom"]), "r1", config)
    assert rec.offer("odom", _odom(1))
    wait_for(lambda: rec.failed, 10, "the split to fail")
    assert not rec.offer("odom", _odom(2))
    rec.close()
    stats = rec.stats()
    assert stats["written"] == {"odom": 1} and stats["dropped"] == {"odom": 1} and stats["failed"] == rec.failed
    with path.open("rb") as f:  # the first part was finished before the split failed
        assert [m.data for _, _, m in make_reader(f).iter_messages()] == [_odom(1)]


def test_the_shipped_foxglove_layout_is_current_and_shows_only_view_topics() -> None:
    import json
    import re

    from ovamos.record.layout import LAYOUT_FILE, layout
    from ovamos.record.views import TOPICS
    shipped = LAYOUT_FILE.read_text()
    assert shipped == layout().to_json() + "\n"  # regenerate: python -m ovamos.record.layout
    shown = set(re.findall(r'"(/[a-z/_]+)"', json.dumps(json.loads(shipped))))
    assert shown and shown <= set(TOPICS)
