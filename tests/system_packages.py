"""Tests that skip for want of a Debian package beyond Python name it in their reason, as
``(system package NAME)`` or ``(system packages A B)``; the run's last line counts them by
package with the one command that installs them all (tests/conftest.py's
``pytest_sessionfinish``; the list: .ci/run's APT_PACKAGES)."""

import re
from collections import Counter

INSTALL_SYSTEM_PACKAGES = "sudo tools/install_system_packages.sh"
_SYSTEM_PACKAGES = re.compile(r"\(system packages? ([^()]+)\)")


def skipped_for_system_packages(reports) -> Counter:
    """Skipped tests by the system package their reason names (a test needing two counts for
    both): ``{package: tests}``, and ``None`` the number of tests."""
    counts: Counter = Counter()
    for rep in reports:
        longrepr = rep.longrepr
        reason = longrepr[2] if isinstance(longrepr, tuple) else str(longrepr)
        found = {p for m in _SYSTEM_PACKAGES.finditer(reason) for p in m.group(1).split()}
        counts.update(found)
        counts[None] += bool(found)
    return counts


def system_packages_line(reports) -> str | None:
    """The run's last line when tests were skipped for want of system packages, else None."""
    counts = skipped_for_system_packages(reports)
    if not counts[None]:
        return None
    named = ", ".join(f"{p} ({n})" for p, n in sorted(counts.items(), key=str) if p)
    return (
        f"{counts[None]} tests skipped for want of system packages: {named}; "
        f"install them with: {INSTALL_SYSTEM_PACKAGES}"
    )
