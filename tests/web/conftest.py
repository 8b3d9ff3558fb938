"""The session fixture (daemons as processes, a signaling server here) for the pages' attack
tests."""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "session"))

from session_helpers import session  # noqa: E402, F401 - the fixture
