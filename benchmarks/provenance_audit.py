"""Which records behind the README and docs lack a spec hash, a commit or a CPU model: the provenance audit.

A number on a page is as good as the record it comes from. A record qualifies when it names

* its spec's SHA-256 (``spec_sha256``: a study's spec, a benchmark script's measurement spec, a model
  evaluation's configuration),
* the commit that made it (``machine.commit`` or ``provenance.commit``; for a study record, every run's too),
* the CPU model (``machine.cpu`` or ``provenance.cpu``, not just ``x86_64``; for a study record, every run's).

A page cites a record by its file name (``envs.json``) or by the name of a study whose record it is (a
spec in benchmarks/studies, benchmarks/confirmatory or benchmarks/pending: its ``record.path`` for a study
made before the study engine, else ``benchmarks/results/<name>.json``). ``command_timings.json`` is judged
by its entries the page quotes (each "M min S s" of the page, matched to the second). The journal is a dated
log and is not audited.

    python benchmarks/provenance_audit.py            # prints the table
    python benchmarks/provenance_audit.py --write    # also writes docs/provenance.md (tests check it is current)

A commit a record names must be one of this repository's history (``commits_outside_history``; the test
suite checks it in a full clone): a record made on a branch that was rebased before it merged names a
commit that no longer exists, and says nothing about the code that made it.
"""

from __future__ import annotations

import argparse
import json
import re
import subprocess
from dataclasses import dataclass
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results"
SPEC_DIRS = ("benchmarks/studies", "benchmarks/confirmatory", "benchmarks/pending")
PAGE = ROOT / "docs" / "provenance.md"
#: a CPU entry that names no model
NO_MODEL = {"", "x86_64", "unknown", "amd64", "aarch64"}
#: a duration as the pages write one: "16 min 13 s"
DURATION = re.compile(r"\b(\d+) min (\d+) s\b")
#: a token that may name a record or a study
TOKEN = re.compile(r"[A-Za-z0-9_+.\-]+")


@dataclass(frozen=True)
class Lack:
    """What one record misses: a sorted tuple of ``spec hash``, ``commit``, ``CPU model``."""

    record: str
    missing: tuple[str, ...]


def pages(root: Path = ROOT) -> list[Path]:
    """The README and every Markdown page under docs/ but the journal and this audit's own page."""
    docs = [p for p in sorted((root / "docs").rglob("*.md")) if "journal" not in p.relative_to(root / "docs").parts]
    return [root / "README.md", *[p for p in docs if p != root / "docs" / PAGE.name]]


def _commit_and_cpu(entry: dict) -> tuple[bool, bool]:
    """Whether a machine or provenance entry names a commit and a CPU model."""
    commit = str(entry.get("commit") or "").strip()
    cpu = str(entry.get("cpu") or "").strip()
    return bool(commit) and commit != "unknown", cpu.lower() not in NO_MODEL


def missing_of(record: dict) -> tuple[str, ...]:
    """What a record (a JSON object) lacks of spec hash, commit and CPU model; empty when it qualifies."""
    where = record.get("machine") or record.get("provenance") or {}
    commit, cpu = _commit_and_cpu(where) if isinstance(where, dict) else (False, False)
    if isinstance(record.get("commit"), str) and record["commit"] not in ("", "unknown"):
        commit = True
    runs = record.get("runs")
    if isinstance(runs, list) and any(isinstance(r, dict) and "provenance" in r for r in runs):
        # a study record: every run names its own (one without a provenance entry lacks both)
        each = [_commit_and_cpu(r.get("provenance") or {}) if isinstance(r, dict) else (False, False) for r in runs]
        commit = commit and all(c for c, _ in each)
        cpu = cpu and all(c for _, c in each)
    spec = isinstance(record.get("spec_sha256"), str) and re.fullmatch(r"[0-9a-f]{64}", record["spec_sha256"]) is not None
    return tuple(name for name, ok in (("spec hash", spec), ("commit", commit), ("CPU model", cpu)) if not ok)


def slug(name: str) -> str:
    """A name as a Markdown heading's anchor writes it (GitHub drops ``+``, ``.`` and the like)."""
    return re.sub(r"[^a-z0-9_\-]", "", name.lower())


def study_records(root: Path = ROOT) -> dict[str, set[str]]:
    """Each study's name, its anchor slug and its spec's file stem -> the file names of its records in benchmarks/results/.

    A name can have two specs (one made before the study engine in benchmarks/studies, its rerun pending):
    a citation of the name cites both records while both exist.
    """
    out: dict[str, set[str]] = {}
    results = (root / "benchmarks" / "results").resolve()
    for folder in SPEC_DIRS:
        for path in sorted((root / folder).glob("*.yaml")):
            spec = yaml.safe_load(path.read_text()) or {}
            name = spec.get("name")
            record = spec.get("record") if isinstance(spec.get("record"), dict) else None
            target = (path.parent / record["path"]).resolve() if record and "path" in record else results / f"{name}.json"
            if name and target.exists() and target.parent == results:
                # a legacy record's select.include adds the runs of more records (beside it) to the study
                select = record.get("select") if record and isinstance(record.get("select"), dict) else {}
                included = [results / str(f) for f in select.get("include") or []]
                for key in (name, slug(name), path.stem):  # the study's name, its anchor, its spec's file name
                    out.setdefault(key, set()).update([target.name, *(f.name for f in included if f.exists())])
    return out


def quoted_durations(text: str) -> list[tuple[str, int]]:
    """Each "M min S s" that ``text`` writes, with its length in seconds."""
    return [(m.group(0), int(m.group(1)) * 60 + int(m.group(2))) for m in DURATION.finditer(text)]


def measured_second(entry: dict) -> int | None:
    """An entry of command_timings.json's wall-clock to the second; ``None`` for a command that failed."""
    return round(float(entry["wall_s"])) if entry.get("exit_status") == 0 else None


def measured_seconds(entries: list[dict]) -> set[int]:
    """The wall-clocks, to the second, of the successful entries of command_timings.json."""
    return {s for e in entries if (s := measured_second(e)) is not None}


def _timing_lacks(text: str, entries: list[dict]) -> set[str]:
    """What the entries of command_timings.json whose wall-clock the page writes as "M min S s" lack.

    A quoted duration that a qualifying successful entry measured (to the second) lacks nothing, whatever
    other entries of the same second lack; one that no successful entry measured is the docs test's concern.
    """
    lacks: set[str] = set()
    for _, seconds in quoted_durations(text):
        matching = [missing_of(e) for e in entries if measured_second(e) == seconds]
        if matching and all(matching):
            lacks |= set(matching[0])
    return lacks


def audit(root: Path = ROOT) -> dict[str, list[Lack]]:
    """Each audited page (relative path) -> the records it cites that lack something, sorted by name."""
    results = root / "benchmarks" / "results"
    files = {p.name for p in results.glob("*.json")}
    studies = study_records(root)
    lacks: dict[str, tuple[str, ...]] = {}
    for name in files - {"command_timings.json"}:
        try:
            record = json.loads((results / name).read_text())
        except (json.JSONDecodeError, UnicodeDecodeError):
            lacks[name] = ("readable JSON",)
            continue
        lacks[name] = missing_of(record) if isinstance(record, dict) else ("spec hash", "commit", "CPU model")
    timings_path = results / "command_timings.json"
    timings = json.loads(timings_path.read_text()) if timings_path.exists() else []
    out: dict[str, list[Lack]] = {}
    for page in pages(root):
        text = page.read_text()
        cited: set[str] = set()
        for token in TOKEN.findall(text):
            token = token.rstrip(".")
            if token in files:
                cited.add(token)
            # a study's name, its section anchor or its spec's file name
            names = [token, *(token[: -len(s)] for s in ("-exploratory", "-confirmatory", ".yaml") if token.endswith(s))]
            for name in names:
                cited |= studies.get(name, set()) | studies.get(slug(name), set())
        found = [Lack(name, lacks[name]) for name in sorted(cited - {"command_timings.json"}) if lacks[name]]
        short = sorted(_timing_lacks(text, timings))
        if short:
            found.append(Lack("command_timings.json (its quoted entries)", tuple(short)))
        if found:
            out[page.relative_to(root).as_posix()] = sorted(found, key=lambda lack: lack.record)
    return out


def render(found: dict[str, list[Lack]]) -> str:
    """docs/provenance.md: the audit as a page, one row per record with the pages that cite it."""
    by_record: dict[str, tuple[tuple[str, ...], list[str]]] = {}
    for page, lacks in found.items():
        for lack in lacks:
            by_record.setdefault(lack.record, (lack.missing, []))[1].append(page)
    lines = [
        "# Provenance audit: records that lack a spec hash, a commit or a CPU model",
        "",
        "Generated by `python benchmarks/provenance_audit.py --write` (the test suite checks that it is current).",
        "A number on a page is as good as its record; a record qualifies when it names its spec's SHA-256, the",
        "commit that made it and the CPU model as the machine reports its name (`AMD EPYC`, `Intel(R) Xeon(R)",
        "Processor`; the records' `cpu_id` adds family, model and stepping), and for a study record every run's",
        "commit and CPU too. Each record below is cited by the pages beside it, by file name or by the name of",
        "the study whose record it is, and does not qualify; the pages say so where they quote it. The journal",
        "is a dated log and is not audited. How these records are to be replaced is in",
        "[confirmatory.md](confirmatory.md#numbers-from-records-that-name-their-spec-commit-and-cpu-model).",
        "",
        f"{len(by_record)} such records, cited by {len(found)} pages.",
        "",
        "| record | lacks | cited by |",
        "|---|---|---|",
    ]
    for record, (missing, cited_by) in sorted(by_record.items()):
        lines.append(f"| `{record}` | {', '.join(missing)} | {', '.join(sorted(cited_by))} |")
    return "\n".join(lines) + "\n"


def _named_commits(value: object, found: set[str]) -> None:
    """Every hexadecimal ``commit`` a record's JSON holds, at any depth (``+uncommitted changes`` cut off)."""
    if isinstance(value, dict):
        for key, item in value.items():
            if key == "commit" and isinstance(item, str):
                head = item.split("+", 1)[0].strip()
                if re.fullmatch(r"[0-9a-f]{7,40}", head):
                    found.add(head)
            else:
                _named_commits(item, found)
    elif isinstance(value, list):
        for item in value:
            _named_commits(item, found)


def commits_outside_history(root: Path = ROOT) -> dict[str, list[str]] | None:
    """Each record of benchmarks/results/ -> the commits it names that ``git rev-list HEAD`` does not hold.

    ``None`` where the history cannot say: not a git checkout, or a shallow clone.
    """

    def git(*args: str) -> subprocess.CompletedProcess[str]:
        return subprocess.run(["git", "-C", str(root), *args], capture_output=True, text=True)

    shallow = git("rev-parse", "--is-shallow-repository")
    if shallow.returncode != 0 or shallow.stdout.strip() != "false":
        return None
    history = git("rev-list", "HEAD").stdout.split()
    out: dict[str, list[str]] = {}
    for path in sorted((root / "benchmarks" / "results").glob("*.json")):
        named: set[str] = set()
        _named_commits(json.loads(path.read_text()), named)
        unknown = sorted(c for c in named if not any(full.startswith(c) for full in history))
        if unknown:
            out[path.name] = unknown
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--write", action="store_true", help=f"write {PAGE.relative_to(ROOT)}")
    args = parser.parse_args()
    text = render(audit())
    print(text, end="")
    if args.write:
        PAGE.write_text(text)
        print(f"wrote {PAGE.relative_to(ROOT)}")


if __name__ == "__main__":
    main()
