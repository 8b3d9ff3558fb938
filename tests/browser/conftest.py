"""Browser tests: scenarios run in a fresh network namespace with headless Chromium (see
netns.py); skipped with the reason where Chromium, playwright or unshare is missing. One that
starts the daemons or a demo holds the suite's slot for a whole session (tests/session_slot.py);
its deadline scales with the machine's load (``session_slot.time_scale``). The fixture that runs
them, ``browser_scenario``, is in tests/conftest.py: tests elsewhere check a scenario's session
too (tests/session's ``demo_run`` is the console_video scenario's demo)."""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
