"""Make the README's and docs' pictures of the two pages again: runs the browser scenarios
that take them (tests/browser/netns.py) and copies their screenshots into docs/img.

    python tools/page_screenshots.py            # all of them (a few minutes)
    python tools/page_screenshots.py console    # only the console's
"""

from __future__ import annotations

import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
NETNS = REPO / "tests" / "browser" / "netns.py"
# scenario -> {screenshot it saves: picture in docs/img}
PICTURES = {
    "console_page": {
        "console_page_live.png": "console_live.png",
        "console_page_frozen.png": "console_frozen.png",
        "console_page_stale.png": "console_stale.png",
    },
    "console_load": {
        "console_load_slow.png": "console_slow.png",
        "console_load_empty.png": "console_empty.png",
    },
    "demo_pages": {"console_sim.png": "console_sim.png"},
    "headset_feed": {"headset_pairing.png": "headset_pairing.png"},
    "headset_session": {
        "session_following.png": "headset_following.png",
        "session_calibrating_3.png": "headset_calibrating.png",
        "session_stale.png": "headset_stale.png",
    },
}
GROUPS = {
    "console": ("console_page", "console_load", "demo_pages"),
    "headset": ("headset_session", "headset_feed"),
}


def main(argv: list[str]) -> int:
    scenarios = [s for g in (argv or GROUPS) for s in GROUPS[g]]
    for name in scenarios:
        out = Path(tempfile.mkdtemp(prefix=f"humantele-{name}-"))
        cmd = [sys.executable, str(NETNS), name, "--out", str(out), "--arg", "pictures=true"]
        print(f"{name} ...", flush=True)
        if subprocess.run(cmd, stdout=subprocess.DEVNULL).returncode != 0:
            print(f"{name} failed: its files are in {out}", file=sys.stderr)
            return 1
        for shot, picture in PICTURES[name].items():
            shutil.copyfile(out / shot, REPO / "docs" / "img" / picture)
            print(f"  docs/img/{picture}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
