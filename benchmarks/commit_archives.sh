#!/usr/bin/env bash
# Commit the archives of studies while they train, so that a machine lost mid-study loses no finished run.
#
#   benchmarks/commit_archives.sh [--every MINUTES] [--checkpoints] SPEC...   # from the repository root; Ctrl-C ends it
#
# Every MINUTES (default 10), for each SPEC, it runs `pimbrl study archive SPEC` (which says so and does
# nothing else when the study has no run directory yet, or has not started in it, as a queued study) and,
# where the archive (archive/<study name> beside the spec) changed, commits that folder alone: "Archive:
# NAME N of TOTAL" (N the archived finished runs, TOTAL the spec's runs). With --checkpoints, each
# interrupted run (a study stopped at its --time-limit) is carried too, its checkpoint xz-compressed, so that
# the next machine resumes it where it stopped; a run's carried copy goes when its finished copy comes. Nothing else in the working tree is staged or committed (paths are literal, not patterns).
# The commit holds the archive's lock, the one `pimbrl study archive` and `pimbrl study run --keep-archive`
# take, so it never commits a half-copied run; when another process holds it, or the commit fails, the
# folder is unstaged again and left to the next round. `pimbrl study run SPEC --keep-archive` archives each
# run as it finishes; this script adds the commits (docs/studies.md).
set -uo pipefail
export GIT_LITERAL_PATHSPECS=1
every=10
carry=""
while [[ "${1:-}" == --* ]]; do
    case "$1" in
        --every)
            every="${2:-}"
            [[ "$every" =~ ^[1-9][0-9]*$ ]] || { echo "--every needs a whole number of minutes, e.g. --every 10" >&2; exit 2; }
            shift 2 ;;
        --checkpoints) carry="--checkpoints"; shift ;;
        *) echo "unknown option $1: the options are --every MINUTES and --checkpoints" >&2; exit 2 ;;
    esac
done
(($# > 0)) || { echo "usage: $0 [--every MINUTES] [--checkpoints] SPEC..." >&2; exit 2; }
pimbrl="${PIMBRL:-.venv/bin/pimbrl}"
python="$(dirname "$pimbrl")/python"
[[ -x "$pimbrl" && -x "$python" ]] || { echo "$pimbrl not found: run from the repository root or set PIMBRL" >&2; exit 2; }
names=()
for spec in "$@"; do
    name=$("$python" -c 'import sys; from pimbrl.experiments.spec import load_spec; print(load_spec(sys.argv[1]).name)' "$spec") \
        || { echo "cannot read the spec $spec (the line above says why)" >&2; exit 2; }
    names+=("$name")
done
commit() {  # archive folder, message: stage and commit the folder alone, or unstage it again
    git add -- "$1" && git commit -q -m "$2" -- "$1" && return 0
    git reset -q -- "$1"
    return 1
}
while true; do
    for i in "${!names[@]}"; do
        spec="${@:i+1:1}" name="${names[i]}"
        "$pimbrl" study archive "$spec" ${carry:+"$carry"} || continue
        archive="$(dirname "$spec")/archive/$name"
        [[ -d "$archive" && -n "$(git status --porcelain -- "$archive")" ]] || continue
        n=$(find "$archive" -name config.json -not -path '*.copying*' -not -path '*.carrying*' -not -path "$archive/.interrupted/*" | wc -l)
        # the plan's last line, "N runs of study NAME ...": its first word (a plan sentence may name a seed too)
        total=$("$pimbrl" study plan "$spec" 2>/dev/null | tail -n 1 | grep -oE '^[0-9]+') || total="?"
        export -f commit
        flock -n "$archive" bash -c 'commit "$0" "$1"' "$archive" "Archive: $name $n of $total" \
            || echo "$archive: not committed this round (busy or git failed); the next round tries again" >&2
    done
    sleep $((every * 60))
done
