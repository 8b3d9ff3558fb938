"""Session recordings in MCAP: schemas, a non-blocking recorder, a crash-tolerant reader.

Daemons use :class:`Recorder`; analysis uses :func:`read_recording`. See docs/analysis.md.
:mod:`.device_file` is the device recording file (``humantele devices record``) and its
reader, which the replay backends of tracking, forcesense and video read.
"""

from humantele.recording.reader import Recording, RecordingReadError, read_recording
from humantele.recording.schemas import CHANNELS, check_participant_id
from humantele.recording.writer import (
    McapLog,
    Recorder,
    RecorderConfig,
    RecorderStats,
    RecordingError,
    role_path,
)

__all__ = [
    "CHANNELS",
    "McapLog",
    "Recorder",
    "RecorderConfig",
    "RecorderStats",
    "Recording",
    "RecordingError",
    "RecordingReadError",
    "check_participant_id",
    "read_recording",
    "role_path",
]
