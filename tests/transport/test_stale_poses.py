"""The pose sender never queues stale poses behind a stalled transport (no network, no timing):
a fake data channel stops draining; the link keeps one newest pose and sends it first on resume."""

from humantele.transport import LinkConfig, PeerLink
from humantele.transport.link import _Peer
from humantele.wire import PoseMessage

Q = (0.0, 0.0, 0.0, 1.0)


class StallingChannel:
    """A data channel whose SCTP buffer drains only when :meth:`drain` is called (as aiortc's
    bufferedAmount / bufferedamountlow behave: the event fires on crossing the threshold)."""

    def __init__(self) -> None:
        self.readyState = "open"
        self.bufferedAmount = 0
        self.bufferedAmountLowThreshold = 0
        self.queued: list[bytes] = []  # accepted, not yet on the wire
        self.wire: list[bytes] = []
        self._handlers: dict[str, list] = {}

    def on(self, event: str, handler=None):
        self._handlers.setdefault(event, []).append(handler)
        return handler

    def send(self, data: bytes) -> None:
        self.queued.append(data)
        self.bufferedAmount += len(data)

    def drain(self) -> None:
        """The transport takes one queued message (as aiortc's flush does per message)."""
        data = self.queued.pop(0)
        self.wire.append(data)
        before = self.bufferedAmount
        self.bufferedAmount -= len(data)
        if before > self.bufferedAmountLowThreshold >= self.bufferedAmount:
            for h in self._handlers.get("bufferedamountlow", []):
                h()


def _link_with(channels: dict, **config) -> tuple[PeerLink, _Peer]:
    link = PeerLink("expert", LinkConfig(**config))
    peer = _Peer(pc=None, channels=channels)
    for name in ("pose", "state"):
        link._watch_binary(peer, name)
    peer.open = True
    link._peer = peer
    return link, peer


def _pose(seq: int) -> PoseMessage:
    return PoseMessage(seq, 0.001 * seq, (0.0, 0.1, 0.0), Q)


def test_a_stalled_channel_holds_one_pose_and_the_newest_goes_first_on_resume():
    pose = StallingChannel()
    link, peer = _link_with({"pose": pose, "state": StallingChannel(), "control": object()})
    size = len(_pose(1).encode())
    ahead = link.config.newest_only_above_bytes // size + 1  # taken before the stall shows
    for seq in range(1, 501):  # 0.5 s at 1 kHz with nothing acknowledged
        assert link.send_pose(_pose(seq))
    # bounded: the few the transport took before it stalled, plus one waiting newest pose
    assert 1 <= ahead <= 4
    assert [PoseMessage.decode(d).seq for d in pose.queued] == list(range(1, ahead + 1))
    assert PoseMessage.decode(peer.pending["pose"]).seq == 500
    assert link.counters.dropped["pose:superseded"] == 500 - ahead - 1
    pose.drain()  # the transport resumes: the newest pose is next after those already taken
    assert PoseMessage.decode(pose.queued[-1]).seq == 500
    assert "pose" not in peer.pending
    while pose.queued:
        pose.drain()
    assert [PoseMessage.decode(d).seq for d in pose.wire] == [*range(1, ahead + 1), 500]
    link.send_pose(_pose(501))  # then the stream goes on as usual
    assert PoseMessage.decode(pose.queued[0]).seq == 501
    assert link.counters.sent["pose"] == ahead + 2


def test_the_fifo_sender_queues_stale_poses_up_to_its_cap():
    """The old behaviour (kept for comparison): every pose queues until the byte cap."""
    pose = StallingChannel()
    link, _ = _link_with(
        {"pose": pose, "state": StallingChannel(), "control": object()},
        send_newest_only=False,
        max_buffered_bytes=2048,
    )
    for seq in range(1, 501):
        link.send_pose(_pose(seq))
    size = len(_pose(1).encode())
    assert len(pose.queued) == 2048 // size + 1  # the backlog the newest waits behind
    assert PoseMessage.decode(pose.queued[0]).seq == 1
    assert link.counters.dropped["pose:backpressure"] == 500 - len(pose.queued)


def test_a_pending_pose_of_a_replaced_peer_connection_is_not_sent():
    old = StallingChannel()
    link, peer = _link_with({"pose": old, "state": StallingChannel(), "control": object()})
    for seq in range(1, 11):
        link.send_pose(_pose(seq))
    assert "pose" in peer.pending
    taken = len(old.queued)
    link._peer = None  # the link was lost and renegotiated
    while old.queued:
        old.drain()
    assert [PoseMessage.decode(d).seq for d in old.wire] == list(range(1, taken + 1))
