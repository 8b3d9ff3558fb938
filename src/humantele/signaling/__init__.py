"""Signaling: a WebSocket server with rooms (one expert, one follower each) that relays complete
SDP offers and answers, and the client the transport uses to talk to it.

Protocol (JSON text messages, one object each, at most ``max_message_bytes``):

client -> server
    ``{"type": "join", "room": str, "role": "expert"|"follower", "token": str, "protocol": 1}``
    must be the first message (within ``join_timeout_s``) and comes once;
    ``{"type": "offer", "sdp": str, "id": int}`` (expert only),
    ``{"type": "answer", "sdp": str, "id": int}`` (follower only; ``id`` echoes the offer's).
server -> client
    ``{"type": "joined", "room", "role", "peer_present": bool}`` after a good join, with
    ``"ice_servers": [{"urls": [...], "username": "<expiry>:<peer id>", "credential": str}]``
    when the server issues time-limited TURN credentials (:mod:`humantele.signaling.turn`);
    ``{"type": "ice_servers", "ice_servers": [...]}``: fresh ones, every ``ttl_s / 2``;
    ``{"type": "peer_joined", "role"}`` / ``{"type": "peer_left", "role"}`` about the other peer;
    relayed ``offer`` / ``answer``;
    ``{"type": "error", "reason": str}`` then the socket closes with one of the codes below.

aiortc has no trickle ICE: descriptions are complete after ``setLocalDescription``, so there
are no candidate messages. A peer whose process died rejoins by connecting again; the server
tells the other side, which negotiates a new peer connection.
"""

from humantele.signaling.messages import (
    CLOSE_BAD_MESSAGE,
    CLOSE_JOIN_TIMEOUT,
    CLOSE_OUT_OF_ORDER,
    CLOSE_ROOM_FULL,
    CLOSE_UNAUTHORIZED,
    SIGNALING_PROTOCOL,
)

__all__ = [
    "CLOSE_BAD_MESSAGE",
    "CLOSE_JOIN_TIMEOUT",
    "CLOSE_OUT_OF_ORDER",
    "CLOSE_ROOM_FULL",
    "CLOSE_UNAUTHORIZED",
    "SIGNALING_PROTOCOL",
]
