"""A child target whose module takes a while to import (as the sensing and video children's
do on a loaded machine): it says when the import starts, then when its target runs."""

import os
import time
from pathlib import Path

_FLAGS = Path(os.environ["HUMANTELE_TEST_FLAGS"])
(_FLAGS / "importing").write_text("1")
end = time.monotonic() + 30.0
while not (_FLAGS / "go").exists() and time.monotonic() < end:  # the test's SIGINT first
    time.sleep(0.02)


def run() -> None:
    (_FLAGS / "ran").write_text("1")
