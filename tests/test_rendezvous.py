"""Tests of the rendezvous book: requests, arrivals, timeouts and releases."""
import numpy as np
import pytest

from em_exploration_ros.core.planning.rendezvous import RendezvousBook, meeting_timeout_s


def test_rendezvous_completes_when_both_arrive() -> None:
    book = RendezvousBook()
    point = np.array([20.0, 10.0])
    meeting = book.request(requester_id=0, partner_id=2, meeting_point=point, time_s=5.0,
                           timeout_s=120.0, rendezvous_id=7)
    assert meeting.deadline_s == pytest.approx(125.0)
    np.testing.assert_allclose(book.is_waiting(2), point)
    assert book.is_waiting(0) is None and book.is_waiting(1) is None
    assert book.arrived(2, 30.0) == []
    np.testing.assert_allclose(book.is_waiting(2), point)
    done = book.arrived(0, 40.0)
    assert [m.rendezvous_id for m in done] == [7]
    assert book.is_waiting(2) is None and book.open_meetings() == []


def test_requester_waits_after_arriving_first() -> None:
    book = RendezvousBook()
    book.request(1, 0, np.array([5.0, 5.0]), time_s=0.0, timeout_s=120.0)
    assert book.arrived(1, time_s=10.0) == []
    np.testing.assert_allclose(book.is_waiting(1), [5.0, 5.0])
    assert len(book.arrived(0, time_s=20.0, requester_id=1)) == 1
    assert book.is_waiting(1) is None


def test_rendezvous_timeout_release_and_replacement() -> None:
    book = RendezvousBook()
    book.request(0, 1, np.array([1.0, 1.0]), time_s=0.0, timeout_s=100.0)
    book.request(2, 1, np.array([9.0, 9.0]), time_s=50.0, timeout_s=100.0)
    np.testing.assert_allclose(book.is_waiting(1), [1.0, 1.0])  # earliest request wins
    assert book.expire(99.0) == []
    expired = book.expire(100.0)
    assert [m.requester_id for m in expired] == [0]
    np.testing.assert_allclose(book.is_waiting(1), [9.0, 9.0])
    # Requester 2 is declared dead: the partner stops waiting.
    assert [m.requester_id for m in book.release(2)] == [2]
    assert book.is_waiting(1) is None
    # A new request of the same requester replaces its previous one.
    book.request(0, 1, np.array([1.0, 1.0]), time_s=200.0, timeout_s=100.0)
    book.request(0, 2, np.array([3.0, 3.0]), time_s=210.0, timeout_s=100.0)
    assert [m.partner_id for m in book.open_meetings()] == [2]
    assert book.is_waiting(1) is None
    # An arrival after the deadline does not complete the meeting.
    assert book.arrived(2, 400.0) == [] and book.open_meetings() == []
    with pytest.raises(ValueError):
        book.request(3, 3, np.zeros(2), 0.0, 10.0)


def test_each_meeting_keeps_its_own_wait_limit_and_releases_by_id() -> None:
    assert meeting_timeout_s(30.0, 1.0, 2.0, 20.0) == pytest.approx(80.0)
    assert meeting_timeout_s(-1.0, 1.0, 2.0, 20.0) == pytest.approx(20.0)
    book = RendezvousBook()
    book.request(0, 1, np.array([1.0, 1.0]), time_s=0.0, timeout_s=30.0, rendezvous_id=4)
    book.request(2, 1, np.array([9.0, 9.0]), time_s=0.0, timeout_s=300.0, rendezvous_id=8)
    assert [m.requester_id for m in book.expire(30.0)] == [0]
    assert book.meeting_of(2).deadline_s == pytest.approx(300.0)
    assert book.release_meeting(2, 7) == []  # an older or unknown id closes nothing
    assert [m.rendezvous_id for m in book.release_meeting(2, 8)] == [8]
    assert book.meeting_of(2) is None and book.open_meetings() == []
