import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parent.parent / "session"))

from session_helpers import session  # noqa: E402, F401 - the loopback session fixture
