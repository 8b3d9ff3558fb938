#!/usr/bin/env bash
# Vendor the JavaScript the pages use, from the npm registry, as built files (no build step,
# no CDN at run time):
#   three.js -> src/humantele/follower/web/vendor/three/ (the headset page)
#   IWER     -> tests/browser/vendor/iwer/ (Meta's WebXR emulator; browser tests only)
# Each folder gets VERSION (package@version) and SHA256SUMS (`sha256sum -c SHA256SUMS` checks
# it; tests/test_vendored_js.py does too): what was vendored, and that nobody edited it since.
# Usage: tools/vendor_js.sh [THREE_VERSION] [IWER_VERSION]   (needs npm; then run the tests,
# check `git diff --stat`, and commit with the versions in the message)
set -euo pipefail
THREE_VERSION=${1:-0.187.0}
IWER_VERSION=${2:-2.5.0}
cd "$(dirname "$0")/.."
tmp=$(mktemp -d)
trap 'rm -rf "$tmp"' EXIT
(cd "$tmp" && npm pack --silent "three@$THREE_VERSION" "iwer@$IWER_VERSION" >/dev/null)
mkdir "$tmp/three" "$tmp/iwer"
tar xzf "$tmp/three-$THREE_VERSION.tgz" -C "$tmp/three"
tar xzf "$tmp/iwer-$IWER_VERSION.tgz" -C "$tmp/iwer"

three=src/humantele/follower/web/vendor/three
rm -rf "$three"
mkdir -p "$three/addons/controls"
cp "$tmp/three/package/build/three.module.js" "$tmp/three/package/build/three.core.js" \
   "$tmp/three/package/LICENSE" "$three/"
cp "$tmp/three/package/examples/jsm/controls/OrbitControls.js" "$three/addons/controls/"
echo "three@$THREE_VERSION" > "$three/VERSION"

iwer=tests/browser/vendor/iwer
rm -rf "$iwer"
mkdir -p "$iwer"
cp "$tmp/iwer/package/build/iwer.min.js" "$tmp/iwer/package/LICENSE" "$iwer/"
echo "iwer@$IWER_VERSION" > "$iwer/VERSION"
manifest() {  # SHA256SUMS of every file under $1 (but itself), sorted, paths relative to $1
  (cd "$1" && find . -type f ! -name SHA256SUMS | sed 's|^\./||' | LC_ALL=C sort \
     | xargs sha256sum > SHA256SUMS)
}
manifest "$three"
manifest "$iwer"
echo "vendored three@$THREE_VERSION and iwer@$IWER_VERSION"
