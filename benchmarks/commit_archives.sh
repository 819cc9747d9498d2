#!/usr/bin/env bash
# Commit the archives of studies while they train, so that a machine lost mid-study loses no finished run.
#
#   benchmarks/commit_archives.sh [--every MINUTES] SPEC...      # from the repository root; Ctrl-C ends it
#
# Every MINUTES (default 10), for each SPEC whose run directory exists (runs/<study name>), it runs
# `pimbrl study archive SPEC` and, where the archive (archive/<study name> beside the spec) changed, commits
# that folder alone: "Archive: NAME N of TOTAL" (N the archived runs, TOTAL the spec's runs). Nothing else
# in the working tree is staged or committed. A commit that fails (another git process holds the index) is
# tried again five times, five seconds apart, then left to the next round. `pimbrl study run SPEC
# --keep-archive` archives each run as it finishes; this script adds the commits (docs/studies.md).
set -uo pipefail
every=10
if [[ "${1:-}" == "--every" ]]; then
    every="${2:-}"
    [[ "$every" =~ ^[1-9][0-9]*$ ]] || { echo "--every needs a whole number of minutes, e.g. --every 10" >&2; exit 2; }
    shift 2
fi
(($# > 0)) || { echo "usage: $0 [--every MINUTES] SPEC..." >&2; exit 2; }
pimbrl="${PIMBRL:-.venv/bin/pimbrl}"
[[ -x "$pimbrl" ]] || { echo "$pimbrl not found: run from the repository root or set PIMBRL" >&2; exit 2; }
for spec in "$@"; do
    [[ -f "$spec" ]] || { echo "no spec $spec" >&2; exit 2; }
done
while true; do
    for spec in "$@"; do
        name=$(basename "$spec" .yaml)
        [[ -d "runs/$name" ]] || continue
        "$pimbrl" study archive "$spec" || continue
        archive="$(dirname "$spec")/archive/$name"
        [[ -n "$(git status --porcelain -- "$archive")" ]] || continue
        n=$(find "$archive" -name config.json | wc -l)
        total=$("$pimbrl" study plan "$spec" 2>/dev/null | grep -c " seed [0-9]")
        for _ in 1 2 3 4 5; do
            git add -- "$archive" && git commit -q -m "Archive: $name $n of ${total:-?}" -- "$archive" && break
            sleep 5
        done
    done
    sleep $((every * 60))
done
