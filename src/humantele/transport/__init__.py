"""The session transport: one WebRTC peer connection per session with three data channels
(``pose``, ``state``, ``control``), negotiated through the signaling server, with clock sync.

Public API: :class:`PeerLink`, :class:`LinkConfig`, :class:`IceServer`, :class:`ClockSync`,
:class:`LinkCounters`, ``LinkState``. See :mod:`humantele.transport.link` for the behaviour.
"""

from humantele.transport.clocksync import ClockSync
from humantele.transport.config import IceServer, LinkConfig
from humantele.transport.link import LinkCounters, LinkState, PeerLink

__all__ = ["ClockSync", "IceServer", "LinkConfig", "LinkCounters", "LinkState", "PeerLink"]
