"""Recording a daemon's session: ``[<role>.session]``, its command-line options, opening and
closing the recorder, and the clock-sync log (shared by both daemons)."""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path
from typing import Any

from pydantic import Field, field_validator

from humantele.config import ConfigModel
from humantele.recording.schemas import check_participant_id

log = logging.getLogger(__name__)


class SessionConfig(ConfigModel):
    """The session a daemon records (``[expert.session]``, ``[follower.session]``).

    ``record``: the MCAP file (None: no recording; an existing file is never overwritten).
    The ids are pseudonyms ('F03', 'S1'): a name or an e-mail address is refused, and no
    patient identity is stored anywhere. Both daemons of a session use the same ``session_id``
    (None: a random one) so ``humantele analyze`` joins their files.
    """

    record: str | None = Field(None, description="MCAP file to record to; None: no recording")
    session_id: str | None = Field(
        None, pattern=r"^[A-Za-z0-9_-]{1,64}$", description="None: a random id per run"
    )
    follower_id: str | None = Field(None, description="pseudonym of the follower, e.g. 'F03'")
    sonographer_id: str | None = Field(None, description="pseudonym of the sonographer, e.g. 'S1'")

    @field_validator("follower_id", "sonographer_id")
    @classmethod
    def _pseudonym(cls, v: str | None, info: Any) -> str | None:
        return None if v is None else check_participant_id(v, info.field_name)


def add_session_arguments(parser: argparse.ArgumentParser) -> None:
    """The daemons' recording options (they override ``[<role>.session]``)."""
    parser.add_argument("--record", metavar="FILE", help="record the session to this MCAP file")
    parser.add_argument("--session-id", help="session id shared by both daemons' recordings")
    parser.add_argument("--follower-id", help="follower's pseudonym, e.g. F03 (never a name)")
    parser.add_argument("--sonographer-id", help="sonographer's pseudonym, e.g. S1")


def session_overrides(args: argparse.Namespace, data: dict[str, Any]) -> None:
    """Put the command line's recording options into a daemon config's ``data`` (a dict)."""
    for key in ("record", "session_id", "follower_id", "sonographer_id"):
        value = getattr(args, key, None)
        if value is not None:
            data["session"][key] = value


def open_recorder(role: str, session: SessionConfig, config: Any) -> Any:
    """The daemon's :class:`humantele.recording.Recorder`, or None when it does not record.
    Raises :class:`humantele.recording.RecordingError` (unwritable path, existing file, disk
    full) at start, so a daemon can refuse to run with a clear message."""
    if not session.record:
        return None
    from humantele.recording import Recorder

    return Recorder(
        Path(session.record).expanduser(),
        role,
        session_id=session.session_id,
        follower_id=session.follower_id,
        sonographer_id=session.sonographer_id,
        config=config,
    )


def open_daemon_recording(role: str, session: SessionConfig, config: Any) -> tuple[bool, Any]:
    """``(ok, recorder)`` for daemon ``role``: the recorder (None when it does not record), or
    ok False, with one clear line on stderr, when the path cannot be recorded to."""
    from humantele.recording import RecordingError

    try:
        rec = open_recorder(role, session, config)
    except RecordingError as exc:
        print(f"humantele {role}: {exc}", file=sys.stderr)
        return False, None
    if rec is not None:
        log.info("%s: recording to %s", role, rec.path)
    return True, rec


def close_daemon_recording(role: str, rec: Any) -> None:
    """Close ``rec`` (if any); a failure during the session is logged, never raised."""
    if rec is None:
        return
    stats = rec.close()
    if stats.error:
        log.error("%s: the recording failed during the session: %s", role, stats.error)


class ClockSyncLog:
    """Records a link's clock-sync estimate (``offset_s``: peer clock minus ours, ``rtt_s``)
    each time it changes, at the local time of the exchange it comes from."""

    def __init__(self, topic: str) -> None:
        self.topic = topic
        self._last: object = None

    def update(self, rec: Any, clock: Any) -> None:
        best = clock.best
        if rec is None or best is None or best is self._last:
            return
        self._last = best
        rec.write(self.topic, best.t_local, {"offset_s": best.offset, "rtt_s": best.rtt})


def recorder_stats(rec: Any) -> dict[str, Any] | None:
    """A recorder's counters for a daemon's stats (None when it does not record)."""
    if rec is None:
        return None
    st = rec.stats
    return {
        "path": str(rec.path),
        "session_id": rec.metadata["session_id"],
        "queued": st.queued,
        "written": st.written,
        "dropped": st.dropped_overflow + st.dropped_invalid + st.dropped_failed,
        "dropped_invalid": st.dropped_invalid,
        "last_invalid": st.last_invalid,
        "error": st.error,
    }
