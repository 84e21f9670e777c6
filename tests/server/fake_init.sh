#!/bin/sh
# Test double of `streetsim init LOG --out OUT.ply` for the training-job tests: optionally
# sleeps (LOG/sleep_s), fails (LOG/fail), else copies LOG/source.ply to OUT.
set -e
log="$1"; out="$3"
if [ -f "$log/sleep_s" ]; then sleep "$(cat "$log/sleep_s")"; fi
if [ -f "$log/fail" ]; then echo "fake init: failing as asked" >&2; exit 3; fi
cp "$log/source.ply" "$out"
echo "fake init: wrote $out"
