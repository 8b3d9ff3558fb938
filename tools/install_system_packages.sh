#!/usr/bin/env bash
# The Debian/Ubuntu packages the tests use beyond Python (Chromium for the browser tests,
# coturn for TURN, g++ and OpenIGTLink's C++ library for the independent clients, ...): the
# tests that need one skip without it, and the run's last line says how many and for what.
# The list is .ci/run's APT_PACKAGES (one list for CI and for everyone).
#   sudo tools/install_system_packages.sh          install the missing ones (apt-get)
#   tools/install_system_packages.sh --list        print the list
set -euo pipefail
root="$(cd "$(dirname "$0")/.." && pwd)"
APT_PACKAGES=()
# the APT_PACKAGES=( ... ) and APT_PACKAGES+=( ... ) assignments of .ci/run, as written there
eval "$(awk '/^APT_PACKAGES\+?=\(/ {on = 1} on {print} on && /\)/ {on = 0}' "$root/.ci/run")"
if [ "${#APT_PACKAGES[@]}" -eq 0 ]; then
  echo "no APT_PACKAGES found in $root/.ci/run" >&2
  exit 1
fi
if [ "${1:-}" = "--list" ]; then
  printf '%s\n' "${APT_PACKAGES[@]}"
  exit 0
fi
missing=()
for pkg in "${APT_PACKAGES[@]}"; do
  dpkg -s "$pkg" >/dev/null 2>&1 || missing+=("$pkg")
done
if [ "${#missing[@]}" -eq 0 ]; then
  echo "system packages: all ${#APT_PACKAGES[@]} installed"
  exit 0
fi
echo "system packages: installing ${missing[*]}"
export DEBIAN_FRONTEND=noninteractive
apt-get update -qq
apt-get install -y -qq --no-install-recommends "${missing[@]}"
