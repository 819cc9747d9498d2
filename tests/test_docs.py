"""The Markdown documentation (docs/**/*.md and README.md) reads without project-internal numbering,
with every code fence closed and every relative link pointing at a file that exists."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from .test_provenance_audit import load_audit

ROOT = Path(__file__).resolve().parents[1]

#: "stop 21", "stops 21 and 22", "issue 13", "Issues 12": numbering a reader outside the project cannot follow
INTERNAL_NUMBER = re.compile(r"\b(stops?|issues?)\s+\d+", re.IGNORECASE)
#: an inline link or image, [text](target) or [text](target "title"); the target may be in angle brackets
LINK = re.compile(r"!?\[[^\]]*\]\(\s*(<[^>]*>|[^)\s]+)(?:\s+\"[^\"]*\")?\s*\)")
EXTERNAL = re.compile(r"^(https?:|mailto:)", re.IGNORECASE)


def markdown_files() -> list[Path]:
    return [*sorted((ROOT / "docs").rglob("*.md")), ROOT / "README.md"]


def rel(path: Path) -> str:
    return path.relative_to(ROOT).as_posix()


def fence_lines(text: str) -> list[int]:
    """1-based numbers of the lines that open or close a code fence."""
    return [i for i, line in enumerate(text.splitlines(), 1) if line.lstrip().startswith("```")]


def prose(text: str) -> str:
    """The text outside fenced code blocks and inline code spans, line numbers kept."""
    out, in_fence = [], False
    for line in text.splitlines():
        if line.lstrip().startswith("```"):
            in_fence = not in_fence
            out.append("")
            continue
        out.append("" if in_fence else re.sub(r"`[^`]*`", "", line))
    return "\n".join(out)


def relative_links(text: str) -> list[tuple[int, str]]:
    """(line, target) of each link whose target is a path in this repository (anchor and query removed)."""
    links = []
    for lineno, line in enumerate(prose(text).splitlines(), 1):
        for match in LINK.finditer(line):
            target = match.group(1).strip("<>")
            if EXTERNAL.match(target):
                continue
            path = target.split("#", 1)[0].split("?", 1)[0]
            if path:
                links.append((lineno, path))
    return links


FILES = markdown_files()
IDS = [rel(p) for p in FILES]


def test_the_documentation_is_found() -> None:
    assert (ROOT / "README.md") in FILES
    assert len(FILES) > 5, IDS
    assert any(p.parent.name == "journal" for p in FILES), "docs/journal/ holds no Markdown file"


@pytest.mark.parametrize("path", FILES, ids=IDS)
def test_no_internal_numbering(path: Path) -> None:
    found = [
        f"{rel(path)}:{lineno}: {match.group(0)!r}"
        for lineno, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1)
        for match in INTERNAL_NUMBER.finditer(line)
    ]
    assert not found, "project-internal numbering (say the date, or leave it out):\n" + "\n".join(found)


@pytest.mark.parametrize("path", FILES, ids=IDS)
def test_code_fences_are_closed(path: Path) -> None:
    fences = fence_lines(path.read_text(encoding="utf-8"))
    assert len(fences) % 2 == 0, f"{rel(path)}: an odd number of ``` lines ({len(fences)}), at lines {fences}"


@pytest.mark.parametrize("path", FILES, ids=IDS)
def test_relative_links_resolve(path: Path) -> None:
    broken = [
        f"{rel(path)}:{lineno}: {target}"
        for lineno, target in relative_links(path.read_text(encoding="utf-8"))
        if not (path.parent / target).exists()
    ]
    assert not broken, "links to files that do not exist:\n" + "\n".join(broken)


def test_the_checks_catch_what_they_are_for() -> None:
    """The helpers above on small samples: each check fails on the defect it exists for."""
    assert INTERNAL_NUMBER.search("the runs of stop 21")
    assert INTERNAL_NUMBER.search("(Stops 21 and 22)")
    assert INTERNAL_NUMBER.search("issue  13's target")
    assert INTERNAL_NUMBER.search("Issues 12")
    assert not INTERNAL_NUMBER.search("stopped at 20,000 steps; 2026-11-21; tissue 3; nonstop 4")
    assert len(fence_lines("```bash\nls\n```\n\n```\nopen\n")) % 2 == 1
    assert len(fence_lines("text\n  ```python\n  x = 1\n  ```\n")) % 2 == 0
    sample = (
        "[a](results.md#x) ![f](figures/a.png) [web](https://example.org/a.md) [m](mailto:a@b.c)\n"
        '[here](#local) `[code](not/a/link.md)` [t](<with space.md> "title")\n'
        "```\n[fenced](nope.md)\n```\n"
    )
    assert relative_links(sample) == [(1, "results.md"), (1, "figures/a.png"), (2, "with space.md")]


# ------------------------------------------------------------------------- confirmatory verdicts
#: a row of docs/results.md's table of confirmatory hypotheses: | [study](#...) | id | claim | where | measure | poi | verdict |
VERDICT_ROW = re.compile(r"^\| \[([^\]]+)\]\(#[^)]*\) \| ([^|]+?) \| [^|]*\| ([^|]+?) \| [^|]*\| ([^|]+?) \| ([^|]+?) \|$", re.M)
#: a probability of improvement with its interval, as the results page and the README write it
POI = re.compile(r"\d\.\d\d\s+\[\d\.\d\d,\s+\d\.\d\d\]")


def readme_disagreements(results: str, readme: str) -> list[str]:
    """Each confirmatory verdict of the generated results page that README's Findings do not state.

    The README states each as ``**ID** (STUDY, WHERE): VERDICT`` on one line (the verdict's words up to any
    parenthesis, e.g. ``inconclusive``), and the first ``P = x [lo, hi]`` of that bullet (a line break may fall
    inside it) is the hypothesis's probability of improvement as the results page has it.
    """
    findings = readme.split("## Findings", 1)[-1].split("\n## ", 1)[0]
    missing = []
    for study, hid, where, poi, verdict in VERDICT_ROW.findall(results):
        word = verdict.split(" (")[0].strip()
        pattern = rf"\*\*{re.escape(hid.strip())}\*\* \({re.escape(study)}, {re.escape(where.strip())}\): {re.escape(word)}\b"
        found = re.search(pattern, findings)
        if not found:
            missing.append(f"{hid.strip()} ({study}, {where.strip()}): {word}")
            continue
        bullet = re.split(r"\n\s*(?:[-*+]|\d+[.)])\s|\n\s*\n", findings[found.end() :], maxsplit=1)[0]
        stated = re.search(r"P = (" + POI.pattern + ")", bullet)
        expected = POI.search(poi)
        said = " ".join(stated.group(1).split()) if stated else None
        if (expected.group(0) if expected else None) != said:
            want = expected.group(0) if expected else "none (the results page gives none)"
            missing.append(f"{hid.strip()} ({study}, {where.strip()}): P = {want}, not {said or 'unstated'}")
    return missing


def test_the_readme_findings_state_every_confirmatory_verdict_of_the_results_page() -> None:
    results = (ROOT / "docs" / "results.md").read_text()
    row = "| [c-b](#c-b-confirmatory) | H1a | claim | Burgers-v0 | real steps to -11 | 0.61 [0.40, 0.80] (95%) | inconclusive |"
    readme = "# x\n\n## Findings\n\n- **H1a** (c-b, Burgers-v0): inconclusive, P = 0.61 [0.40, 0.80]\n\n## Next\n"
    assert readme_disagreements(row, readme) == []
    assert readme_disagreements(row, readme.replace("inconclusive", "supported")) == ["H1a (c-b, Burgers-v0): inconclusive"]
    assert readme_disagreements(row, "## Findings\n\n## Other\n- **H1a** (c-b, Burgers-v0): inconclusive\n") != []
    wrong = readme.replace("0.61 [0.40, 0.80]", "0.61 [0.40, 0.81]")
    assert readme_disagreements(row, wrong) == ["H1a (c-b, Burgers-v0): P = 0.61 [0.40, 0.80], not 0.61 [0.40, 0.81]"]
    # the P of the next bullet is not this one's
    nxt = "# x\n\n## Findings\n\n- **H1a** (c-b, Burgers-v0): inconclusive.\n- **H1b** (c-b, Burgers-v0): P = 0.61 [0.40, 0.80]\n"
    assert readme_disagreements(row, nxt) == ["H1a (c-b, Burgers-v0): P = 0.61 [0.40, 0.80], not unstated"]
    broken = readme.replace("P = 0.61 [0.40, 0.80]", "P = 0.61\n  [0.40, 0.80]")  # a line break inside it
    assert readme_disagreements(row, broken) == []
    none = row.replace("0.61 [0.40, 0.80] (95%)", "\u2014")  # no P on the results page: none may be stated
    assert readme_disagreements(none, readme) == [
        "H1a (c-b, Burgers-v0): P = none (the results page gives none), not 0.61 [0.40, 0.80]"
    ]
    # every row of the page's verdict table is read (a row the pattern missed would go unchecked)
    rows = [line for line in results.splitlines() if re.match(r"^\| \[[^\]]+\]\(#[^)]*-confirmatory\) \| H", line)]
    assert len(VERDICT_ROW.findall(results)) == len(rows) > 0
    assert readme_disagreements(results, (ROOT / "README.md").read_text()) == [], "README Findings must state these verdicts"


# ------------------------------------------------------------------------- provenance of the README's numbers
#: a study's provenance line in a generated page: "- **Runs**: N; CPU: ...; commit: ..."
PROVENANCE = re.compile(r"^- \*\*Runs\*\*: [^;]*; CPU: ([^;]*); commit: (.*)\.$", re.M)


#: pages the Findings may link to as a whole: they hold no study's numbers of their own for a claim to rest on
OVERVIEW_PAGES = {"docs/results.md", "docs/confirmatory.md", "docs/control.md", "docs/control/", "docs/journal/README.md"}


def unprovenanced_findings(readme: str, pages: dict[str, str]) -> list[str]:
    """Each study the README's Findings link to whose page names no CPU model or no commit.

    ``pages`` maps a page's path (``docs/results.md``, ``docs/control/NAME/report.md``) to its text; a link
    ``docs/results.md#NAME-kind`` points at the section ``## NAME (kind)`` of that page, a link to a study's
    ``report.md`` at that study; a link to a whole page of many studies cites none of them.
    """
    findings = readme.split("## Findings", 1)[-1].split("\n## ", 1)[0]
    bad = []
    for path, anchor in re.findall(r"\]\((docs/[^)#]*)(?:#([^)]+))?\)", findings):
        if not anchor and path in OVERVIEW_PAGES:  # a page about many studies or the protocol: it cites none
            continue
        if path not in pages:
            bad.append(f"{path}{'#' + anchor if anchor else ''}: not a study's page or section (an overview? see OVERVIEW_PAGES)")
            continue
        text = pages[path]
        if anchor:
            heads = [
                h
                for h in re.findall(r"^## (.+)$", text, re.M)
                if re.sub(r"[^a-z0-9 -]", "", h.lower()).replace(" ", "-") == anchor
            ]
            if not heads:
                bad.append(f"{path}#{anchor}: no such section")
                continue
            text = text.split(f"## {heads[0]}\n", 1)[1].split("\n## ", 1)[0]
        found = PROVENANCE.search(text)
        if found is None or "not recorded" in found.group(1) or "not recorded" in found.group(2):
            bad.append(f"{path}{'#' + anchor if anchor else ''}: {found.group(0) if found else 'no provenance line'}")
    return bad


def test_the_readme_findings_cite_only_records_with_their_cpu_model_and_commit() -> None:
    page = "## a (exploratory)\n\n- **Runs**: 3; CPU: Intel Xeon; commit: abc.\n\n## b (exploratory)\n\n- **Runs**: 3; CPU: not recorded; commit: not recorded.\n"
    pages = {"docs/results.md": page}
    assert unprovenanced_findings("## Findings\n\n- x ([a](docs/results.md#a-exploratory))\n", pages) == []
    assert unprovenanced_findings("## Findings\n\n- x ([b](docs/results.md#b-exploratory))\n", pages) != []
    assert unprovenanced_findings("## Findings\n\n- x ([c](docs/results.md#c-exploratory))\n", pages) != []
    assert unprovenanced_findings("## Findings\n\n## Other\n- x ([b](docs/results.md#b-exploratory))\n", pages) == []
    assert unprovenanced_findings("## Findings\n\n- see [c](docs/confirmatory.md)\n", pages) == []
    assert unprovenanced_findings("## Findings\n\n- -9.1 ([m](docs/models.md))\n", pages) != []  # a page no test reads
    pages = {
        str(p.relative_to(ROOT)): p.read_text()
        for p in [ROOT / "docs" / "results.md", *(ROOT / "docs" / "control").glob("*/report.md")]
    }
    assert unprovenanced_findings((ROOT / "README.md").read_text(), pages) == []


def test_every_spec_with_a_study_record_is_the_text_that_record_was_made_under() -> None:
    """A spec edited after its runs (an arm added, a plan changed) would name runs that never ran: new work goes
    in a new spec, and the record's own copy of the spec is the file."""
    import json

    from pimbrl.experiments.spec import load_spec

    checked = []
    for path in sorted([*(ROOT / "benchmarks").glob("*/*.yaml")]):
        spec = load_spec(path)
        if spec.record is None or spec.record.format != "study" or not spec.record.path.is_file():
            continue
        record = json.loads(spec.record.path.read_text())
        assert record["spec_sha256"] == spec.sha256, (
            f"{path.relative_to(ROOT)} hashes to {spec.sha256[:16]}, but its record was made under {record['spec_sha256'][:16]}"
        )
        checked.append(spec.name)
    assert {"confirmatory-burgers", "control-dpc-ks-horizon", "tune-burgers"} <= set(checked)


# ------------------------------------------------------------------------- the README's timings
def untimed_durations(readme: str, entries: list[dict]) -> list[str]:
    """Each "M min S s" of the README that no successful entry of command_timings.json measured (to the second).

    The provenance audit reads the durations of the pages the same way (benchmarks/provenance_audit.py).
    """
    audit = load_audit()
    measured = audit.measured_seconds(entries)
    return [quoted for quoted, seconds in audit.quoted_durations(readme) if seconds not in measured]


def test_every_timing_in_the_readme_is_a_recorded_measurement() -> None:
    import json

    entries = [{"wall_s": 973.4, "exit_status": 0}, {"wall_s": 61.0, "exit_status": 1}]
    assert untimed_durations("takes 16 min 13 s here", entries) == []
    assert untimed_durations("takes 1 min 1 s here", entries) == ["1 min 1 s"]  # that run failed
    assert untimed_durations("7 min 9 s", entries) == ["7 min 9 s"]
    record = ROOT / "benchmarks" / "results" / "command_timings.json"
    readme = (ROOT / "README.md").read_text()
    assert "command_timings.json" in readme, "the README's timings must name their record"
    assert untimed_durations(readme, json.loads(record.read_text())) == []
