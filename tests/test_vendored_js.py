"""The vendored JavaScript is what its VERSION says, unedited (issue 22 item 5): each folder's
SHA256SUMS (written by tools/vendor_js.sh) names every file with its SHA-256. The three.js
sums were checked against ``npm pack three@0.187.0`` when recorded."""

from __future__ import annotations

import hashlib
import re
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
THREE = REPO / "src" / "humantele" / "follower" / "web" / "vendor" / "three"
IWER = REPO / "tests" / "browser" / "vendor" / "iwer"


def sums(folder: Path) -> dict[str, str]:
    out = {}
    for line in (folder / "SHA256SUMS").read_text().splitlines():
        digest, name = line.split(maxsplit=1)
        assert re.fullmatch(r"[0-9a-f]{64}", digest), line
        out[name.lstrip("*")] = digest
    return out


@pytest.mark.parametrize("folder, package", [(THREE, "three"), (IWER, "iwer")])
def test_every_vendored_file_is_listed_with_its_sha256(folder, package):
    listed = sums(folder)
    present = {
        p.relative_to(folder).as_posix()
        for p in folder.rglob("*")
        if p.is_file() and p.name != "SHA256SUMS"
    }
    assert set(listed) == present, "SHA256SUMS and the files differ: run tools/vendor_js.sh"
    for name, digest in listed.items():
        got = hashlib.sha256((folder / name).read_bytes()).hexdigest()
        assert got == digest, f"{folder.name}/{name} was changed since it was vendored"
    assert re.fullmatch(rf"{package}@\d+\.\d+\.\d+\n", (folder / "VERSION").read_text())


def test_three_js_is_the_version_recorded():
    version = (THREE / "VERSION").read_text().strip().split("@")[1]
    revision = re.search(r"REVISION = '(\d+)'", (THREE / "three.core.js").read_text()).group(1)
    assert version.split(".")[1] == revision  # three 0.187.0 is r187
