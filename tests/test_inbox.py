"""The service inbox: order kept, only the newest of a keep-latest channel, bounded, one taker."""

from __future__ import annotations

import threading
import time

from ovamos.shared.inbox import Inbox


def test_ordinary_events_run_in_order_and_keep_latest_channels_keep_only_the_newest() -> None:
    inbox, ran, dropped = Inbox(), [], []
    inbox.put(ran.append, "task 1")
    for i in range(5):
        inbox.put(ran.append, f"frame {i}", channel="rgbd", keep=1, on_drop=lambda: dropped.append(1))
    inbox.put(ran.append, "task 2")
    assert inbox.pending() == 3
    assert inbox.run_pending() == 3
    assert ran == ["task 1", "frame 4", "task 2"] and len(dropped) == 4


def test_a_keep_n_channel_keeps_its_newest_n_each_at_the_place_it_arrived() -> None:
    inbox, ran = Inbox(), []
    inbox.put(ran.append, "f0", channel="rgbd", keep=2)
    inbox.put(ran.append, "task")
    for i in range(1, 4):
        inbox.put(ran.append, f"f{i}", channel="rgbd", keep=2)
        if i == 2:
            inbox.put(ran.append, "odom", channel="odom", keep=1)
    inbox.run_pending()
    assert ran == ["task", "f2", "odom", "f3"]  # no frame overtakes what came before it


def test_a_stalled_taker_holds_a_bounded_number_of_places() -> None:
    inbox, ran = Inbox(), []
    inbox.put(ran.append, "task")
    for i in range(10_000):
        inbox.put(ran.append, i, channel="rgbd", keep=1)
    assert len(inbox._order) < 100
    inbox.run_pending()
    assert ran == ["task", 9999]


def test_the_ordinary_queue_is_bounded_and_counts_what_it_drops() -> None:
    inbox, ran, dropped = Inbox(limit=3), [], []
    for i in range(5):
        inbox.put(ran.append, i, on_drop=lambda: dropped.append(1))
    inbox.run_pending()
    assert ran == [2, 3, 4] and len(dropped) == 2


def test_events_put_from_other_threads_run_on_the_taking_thread_only() -> None:
    inbox, threads, stop = Inbox(), set(), threading.Event()
    putters = [threading.Thread(target=lambda: [inbox.put(lambda _: threads.add(threading.get_ident()),
                                                          None) for _ in range(200)]) for _ in range(4)]
    for t in putters:
        t.start()
    for t in putters:
        t.join()
    ran = inbox.run_until(time.monotonic() + 1.0, stop)
    assert ran == 800 and threads == {threading.get_ident()}


def test_run_until_returns_at_the_deadline_or_when_closed() -> None:
    inbox = Inbox()
    start = time.monotonic()
    assert inbox.run_until(start + 0.05) == 0 and time.monotonic() >= start + 0.05
    threading.Timer(0.05, inbox.close).start()
    assert inbox.run_until(time.monotonic() + 30) == 0 and inbox.closed
    inbox.put(print, "after close")  # refused silently: nothing runs after close
    assert inbox.pending() == 0


def test_a_sleeping_taker_is_woken_by_a_put_and_by_close_not_by_its_poll() -> None:
    inbox, stop, ran = Inbox(), threading.Event(), []
    result: list[int] = []
    taker = threading.Thread(target=lambda: result.append(
        inbox.run_until(time.monotonic() + 600, stop, max_wait=600)))
    taker.start()
    time.sleep(0.2)  # the taker is asleep: nothing queued
    inbox.put(lambda arg: (ran.append(arg), stop.set()), "woken")
    taker.join(30)  # its own poll would come after 600 s
    assert not taker.is_alive() and ran == ["woken"] and result == [1]

    taker = threading.Thread(target=lambda: result.append(
        inbox.run_until(time.monotonic() + 600, max_wait=600)))
    taker.start()
    time.sleep(0.2)
    inbox.close()
    taker.join(30)
    assert not taker.is_alive() and result == [1, 0]
