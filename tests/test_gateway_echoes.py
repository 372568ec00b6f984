"""The gateway's own publications heard back (awaremw.gateway.echoes), on a fake clock."""

from __future__ import annotations

import pytest

from awaremw.gateway.echoes import Echoes

T = "aware/def/channel/1"
COPY = b'{"attr": "temperature", "period_s": 2.0, "version": 3}'


def test_each_publication_is_recognised_once_when_heard_back() -> None:
    e = Echoes()
    e.sent(T, COPY, 0.0)
    assert e.heard(T, COPY, 0.1)
    assert not e.heard(T, COPY, 0.2)  # a second equal payload is someone else's
    assert len(e) == 0


def test_our_clearing_heard_back_is_ours_and_a_clients_deletion_after_it_is_the_clients() -> None:
    e = Echoes()
    e.sent(T, b"", 0.0)
    assert e.heard(T, b"", 0.05)
    assert not e.heard(T, b"", 1.0)


def test_two_equal_publications_come_back_twice_and_other_topics_are_not_confused() -> None:
    e = Echoes()
    e.sent(T, b"", 0.0)
    e.sent(T, b"", 0.1)
    assert not e.heard("aware/def/channel/2", b"", 0.2)
    assert e.heard(T, b"", 0.2) and e.heard(T, b"", 0.3)
    assert not e.heard(T, b"", 0.4)


def test_a_publication_not_heard_back_within_the_ttl_is_forgotten() -> None:
    """Lost with a broken link or refused by the broker: left waiting, it would
    swallow a client's equal payload (a deletion equal to our clearing) for ever."""
    e = Echoes(ttl=60.0)
    e.connected(0.0)
    e.sent(T, b"", 1.0)
    assert not e.heard(T, b"", 61.5)  # the client's deletion, long after
    assert len(e) == 0


def test_a_reconnect_gives_what_was_sent_before_it_a_new_ttl() -> None:
    """A persistent session delivers after a reconnect what the broker queued while
    we were away: still our echo."""
    e = Echoes(ttl=60.0)
    e.connected(0.0)
    e.sent(T, b"", 1.0)
    e.connected(100.0)
    assert e.heard(T, b"", 130.0)


def test_the_records_are_bounded_per_topic_and_in_topics() -> None:
    e = Echoes(per_topic=2, max_topics=3)
    for i in range(5):
        e.sent(T, b"%d" % i, 0.0)
    assert not e.heard(T, b"0", 0.1) and e.heard(T, b"4", 0.1)  # the oldest dropped
    for i in range(4):
        e.sent(f"aware/def/group/{i}", b"x", 0.0)
    assert len(e) == 3  # T's remaining record went with its topic, the oldest
    assert not e.heard(T, b"3", 0.2)


def test_a_bad_configuration_is_refused() -> None:
    with pytest.raises(ValueError):
        Echoes(ttl=0)
