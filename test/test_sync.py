"""ApproximateTimeSynchronizer (message_filters semantics), LatestMailbox, IMU gravity filter."""

from __future__ import annotations

import threading
import time
from types import SimpleNamespace

import numpy as np
import pytest

from shape_detector.imu_gravity import G, ImuGravityFilter, quaternion_to_matrix
from shape_detector.sync import (
    ApproximateTimeSynchronizer,
    LatestMailbox,
    TimeSynchronizer,
    header_stamp_ns,
    synchronize_offline,
)

MS = 1_000_000


def msg(stamp_ns: int, tag: str = "") -> SimpleNamespace:
    sec, nsec = divmod(stamp_ns, 1_000_000_000)
    return SimpleNamespace(header=SimpleNamespace(stamp=SimpleNamespace(sec=sec, nanosec=nsec)), tag=tag)


def test_header_stamp_variants():
    assert header_stamp_ns(msg(1_500_000_000)) == 1_500_000_000
    ros1 = SimpleNamespace(header=SimpleNamespace(stamp=SimpleNamespace(secs=2, nsecs=5)))
    assert header_stamp_ns(ros1) == 2_000_000_005
    assert header_stamp_ns(SimpleNamespace(data=1)) is None


def test_pairs_within_slop_and_callback():
    sync = ApproximateTimeSynchronizer(2, queue_size=10, slop=0.01)
    got = []
    sync.register_callback(lambda a, b: got.append((a.tag, b.tag)))
    # colour every 200 ms, depth 3 ms later
    for k in range(5):
        t = 1_000_000_000 + k * 200 * MS
        assert sync.add(0, msg(t, f"c{k}")) is None
        out = sync.add(1, msg(t + 3 * MS, f"d{k}"))
        assert out is not None and out[0].tag == f"c{k}" and out[1].tag == f"d{k}"
    assert got == [(f"c{k}", f"d{k}") for k in range(5)]
    assert sync.emitted == 5 and sync.queued() == [0, 0]


def test_outside_slop_never_pairs():
    sync = ApproximateTimeSynchronizer(2, queue_size=10, slop=0.002)
    assert sync.add(0, msg(1000 * MS)) is None
    assert sync.add(1, msg(1003 * MS)) is None
    assert sync.emitted == 0 and sync.queued() == [1, 1]


def test_picks_closest_candidate_and_leaves_older():
    sync = ApproximateTimeSynchronizer(2, queue_size=10, slop=0.05)
    sync.add(1, msg(990 * MS, "d990"))
    sync.add(1, msg(1004 * MS, "d1004"))
    # the colour message arrives: the closest depth (1004) wins, 990 stays queued
    out = sync.add(0, msg(1000 * MS, "c1000"))
    assert out is not None and out[1].tag == "d1004"
    assert sync.queued() == [0, 1]


def test_three_inputs_spread_checked():
    sync = ApproximateTimeSynchronizer(3, queue_size=10, slop=0.01)
    sync.add(0, msg(1000 * MS, "a"))
    sync.add(1, msg(1009 * MS, "b"))  # within slop of a
    # c is within slop of b but a..c spread is 17 ms > 10 ms: no set
    assert sync.add(2, msg(1017 * MS, "c")) is None
    # a closer c completes the set
    out = sync.add(2, msg(1005 * MS, "c2"))
    assert out is not None and [m.tag for m in out] == ["a", "b", "c2"]


def test_queue_overflow_evicts_oldest():
    sync = ApproximateTimeSynchronizer(2, queue_size=3, slop=0.001)
    for k in range(5):
        sync.add(0, msg((1000 + 100 * k) * MS, f"c{k}"))
    assert sync.queued() == [3, 0] and sync.evicted == 2
    # the evicted c0 cannot be matched any more, c2 can
    assert sync.add(1, msg(1000 * MS)) is None
    out = sync.add(1, msg(1200 * MS))
    assert out is not None and out[0].tag == "c2"
    # a message older than a full queue is dropped immediately
    sync2 = ApproximateTimeSynchronizer(1, queue_size=1, slop=0.0)
    assert sync2.add(0, msg(5)) is not None  # single input: emits itself


def test_duplicate_stamp_replaces_and_exact_sync():
    sync = TimeSynchronizer(2, queue_size=5)
    sync.add(0, msg(1000, "old"))
    sync.add(0, msg(1000, "new"))
    assert sync.queued() == [1, 0]
    assert sync.add(1, msg(1001)) is None  # 1 ns off: no exact match
    out = sync.add(1, msg(1000))
    assert out is not None and out[0].tag == "new"


def test_headerless_ignored_unless_stamp_given():
    sync = ApproximateTimeSynchronizer(2, 5, 0.01)
    assert sync.add(0, SimpleNamespace(data=1)) is None
    assert sync.headerless == 1
    sync.add(0, SimpleNamespace(data=1), stamp_ns=10)
    assert sync.add(1, SimpleNamespace(data=2), stamp_ns=12) is not None


def test_configure_validation_and_offline_helper():
    sync = ApproximateTimeSynchronizer(2, 5, 0.01)
    with pytest.raises(ValueError):
        sync.configure(queue_size=0)
    with pytest.raises(ValueError):
        sync.configure(slop=-1)
    with pytest.raises(IndexError):
        sync.add(2, msg(1))
    stream = []
    for k in range(4):
        stream += [(1, msg(k * 100 * MS + 4 * MS)), (0, msg(k * 100 * MS))]
    assert len(synchronize_offline(stream, 2, 10, 0.01)) == 4


def test_thread_safety_many_producers():
    sync = ApproximateTimeSynchronizer(2, queue_size=1000, slop=0.001)
    n = 300

    def feed(i):
        for k in range(n):
            sync.add(i, msg(k * 10 * MS))

    ts = [threading.Thread(target=feed, args=(i,)) for i in range(2)]
    for t in ts:
        t.start()
    for t in ts:
        t.join()
    assert sync.emitted == n and sync.queued() == [0, 0]


def test_mailbox_latest_only():
    box: LatestMailbox[int] = LatestMailbox()
    assert box.get(timeout=0.01) is None
    assert box.put(1) is None
    assert box.put(2) == 1
    assert box.dropped == 1 and box.get(timeout=0) == 2 and box.get(timeout=0.01) is None
    results = []

    def consumer():
        while True:
            item = box.get()
            if item is None:
                return
            results.append(item)
            time.sleep(0.01)  # slow consumer

    t = threading.Thread(target=consumer)
    t.start()
    for k in range(100):
        box.put(k)
        time.sleep(0.0005)
    time.sleep(0.05)
    box.close()
    t.join(timeout=2)
    assert not t.is_alive()
    assert results[-1] == 99  # the newest item is never lost
    assert len(results) + box.dropped - 1 == 100  # every item either taken or dropped
    assert results == sorted(results)
    assert box.put(5) is None and box.get(timeout=0) is None  # closed


def test_mailbox_wait_empty_hands_over_one_item_at_a_time():
    box: LatestMailbox[int] = LatestMailbox()
    assert box.wait_empty(timeout=0)  # empty from the start
    box.put(1)
    assert not box.wait_empty(timeout=0.02)  # nobody took it
    taken = []

    def consumer():
        while (item := box.get()) is not None:
            time.sleep(0.005)
            taken.append(item)

    t = threading.Thread(target=consumer)
    t.start()
    for k in range(2, 40):  # a producer that waits before each put never replaces an item
        assert box.wait_empty(timeout=2.0)
        box.put(k)
    assert box.wait_empty(timeout=2.0)
    box.close()
    t.join(timeout=2)
    assert taken == list(range(1, 40)) and box.dropped == 0
    box2: LatestMailbox[int] = LatestMailbox()
    box2.put(7)
    threading.Timer(0.05, box2.close).start()
    assert box2.wait_empty(timeout=2.0)  # closing wakes a waiting producer


def test_imu_gravity_filter_converges_and_rejects():
    f = ImuGravityFilter(time_constant=0.2)
    assert f.up is None
    rng = np.random.default_rng(0)
    # camera optical frame: up is -y; IMU in the camera frame reads +g along -y at rest
    for k in range(400):
        a = np.array([0.0, -G, 0.0]) + rng.normal(0, 0.5, 3)
        f.update(a, stamp_ns=k * 5 * MS)
    assert np.allclose(f.up, [0, -1, 0], atol=0.05)
    assert not f.update([np.nan, 0, 0]) and not f.update([0, 0, 30.0])  # NaN, hard shake
    assert f.rejected == 2


def test_imu_gravity_rotation():
    # IMU frame z-up, rotated into the optical frame (x right, y down, z forward)
    R = np.array([[1, 0, 0], [0, 0, -1], [0, 1, 0]], dtype=float)  # imu z -> camera -y
    f = ImuGravityFilter(time_constant=0.0, imu_to_camera=R)
    f.update([0, 0, G])
    assert np.allclose(f.up, [0, -1, 0])
    # the same rotation as a quaternion: +90 deg about x
    q = [np.sin(np.pi / 4), 0, 0, np.cos(np.pi / 4)]
    assert np.allclose(quaternion_to_matrix(q), R, atol=1e-9)
    with pytest.raises(ValueError):
        quaternion_to_matrix([0, 0, 0, 0])
