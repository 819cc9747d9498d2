"""The provenance audit: which records behind the pages lack a spec hash, a commit or a CPU model."""

from __future__ import annotations

import importlib.util
import json
import subprocess
import sys
from pathlib import Path
from types import ModuleType

import pytest

ROOT = Path(__file__).resolve().parents[1]
HASH = "ab" * 32


def load_audit() -> ModuleType:
    """benchmarks/provenance_audit.py as a module (loaded once per test process)."""
    name = "provenance_audit_under_test"
    if name in sys.modules:
        return sys.modules[name]
    spec = importlib.util.spec_from_file_location(name, ROOT / "benchmarks" / "provenance_audit.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module  # its dataclass looks its module up there
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def audit() -> ModuleType:
    return load_audit()


def test_a_record_qualifies_only_with_spec_hash_commit_and_cpu_model(audit) -> None:
    good = {"spec_sha256": HASH, "machine": {"commit": "447f5b3", "cpu": "AMD EPYC"}}
    assert audit.missing_of(good) == ()
    assert audit.missing_of({**good, "spec_sha256": "not a hash"}) == ("spec hash",)
    assert audit.missing_of({**good, "machine": {"commit": "unknown", "cpu": "x86_64"}}) == ("commit", "CPU model")
    assert audit.missing_of({"rows": []}) == ("spec hash", "commit", "CPU model")
    # a study record: every run names its commit and CPU too
    study = {"spec_sha256": HASH, "provenance": {"commit": "c1", "cpu": "Intel(R) Xeon(R) Processor"}}
    runs = [{"provenance": {"commit": "c1", "cpu": "AMD EPYC"}}, {"provenance": {"commit": "c2", "cpu": "x86_64"}}]
    assert audit.missing_of({**study, "runs": runs[:1]}) == ()
    assert audit.missing_of({**study, "runs": runs}) == ("CPU model",)
    assert audit.missing_of({**study, "runs": [runs[0], {"seed": 3}]}) == ("commit", "CPU model")  # a run without one
    assert audit.missing_of({**study, "provenance": {"commit": "c1", "cpu": "unknown"}, "runs": runs[:1]}) == ("CPU model",)
    # a timing entry names its commit at the top
    assert audit.missing_of({"spec_sha256": HASH, "commit": "c1", "machine": {"cpu": "AMD EPYC"}}) == ()


def test_a_page_cites_records_by_file_name_by_study_name_and_by_quoted_timing(audit, tmp_path) -> None:
    results = tmp_path / "benchmarks" / "results"
    results.mkdir(parents=True)
    (results / "old.json").write_text(json.dumps({"rows": []}))
    (results / "new.json").write_text(json.dumps({"spec_sha256": HASH, "machine": {"commit": "c", "cpu": "AMD EPYC"}}))
    (results / "legacy_compare.json").write_text(json.dumps({"env": "x"}))
    entries = [
        {"wall_s": 973.4, "exit_status": 0, "machine": {"cpu": "AMD EPYC"}, "commit": "c"},  # 16 min 13 s, no hash
        {"wall_s": 61.0, "exit_status": 1, "machine": {"cpu": "AMD EPYC"}, "commit": "c"},  # failed: not a timing
        {"wall_s": 120.2, "exit_status": 0, "machine": {"cpu": "AMD EPYC"}, "commit": "c"},  # 2 min 0 s, no hash ...
        {"wall_s": 119.8, "exit_status": 0, "machine": {"cpu": "AMD EPYC"}, "commit": "c", "spec_sha256": HASH},  # ... or one
    ]
    (results / "command_timings.json").write_text(json.dumps(entries))
    studies = tmp_path / "benchmarks" / "studies"
    studies.mkdir()
    (studies / "legacy.yaml").write_text("name: legacy-study\nrecord:\n  path: ../results/legacy_compare.json\n")
    (studies / "plus.yaml").write_text(
        "name: partial-x+30\nrecord:\n  path: ../results/plus_old.json\n"
        "  select: {include: [plus_more.json, plus_missing.json]}\n"  # more runs from records beside it
    )
    (results / "plus_old.json").write_text("{}")
    (results / "plus_more.json").write_text("{}")
    for folder in ("confirmatory", "pending"):
        (tmp_path / "benchmarks" / folder).mkdir()
    # the same name pending again through the engine: while both records exist, a citation cites both
    (tmp_path / "benchmarks" / "pending" / "legacy.yaml").write_text("name: legacy-study\nkind: exploratory\n")
    (results / "legacy-study.json").write_text(json.dumps({"rows": 1}))
    (tmp_path / "docs" / "journal").mkdir(parents=True)
    readme = "It took 16 min 13 s (command_timings.json), 1 min 1 s and 2 min 0 s; new.json says 3; ok.json is none.\n"
    (tmp_path / "README.md").write_text(readme)
    (tmp_path / "docs" / "a.md").write_text("From `old.json` and [legacy](results.md#legacy-study-exploratory).\n")
    (tmp_path / "docs" / "b.md").write_text("See [x](results.md#partial-x30-exploratory) and benchmarks/studies/legacy.yaml.\n")
    (tmp_path / "docs" / "journal" / "day.md").write_text("old.json, history, not audited\n")
    found = audit.audit(tmp_path)
    assert sorted(found) == ["README.md", "docs/a.md", "docs/b.md"]
    assert [lack.record for lack in found["docs/a.md"]] == ["legacy-study.json", "legacy_compare.json", "old.json"]
    # an anchor drops the "+"; a spec's file name cites its study
    # a record's select.include cites the records it names (one that does not exist is no record)
    assert [lack.record for lack in found["docs/b.md"]] == [
        "legacy-study.json",
        "legacy_compare.json",
        "plus_more.json",
        "plus_old.json",
    ]
    # 16 min 13 s lacks the hash; 1 min 1 s failed; 2 min 0 s has a qualifying entry of the same second
    assert [(lack.record, lack.missing) for lack in found["README.md"]] == [
        ("command_timings.json (its quoted entries)", ("spec hash",))
    ]
    entries[0]["spec_sha256"] = HASH
    (results / "command_timings.json").write_text(json.dumps(entries))
    assert "README.md" not in audit.audit(tmp_path)
    page = audit.render(found)
    assert "| `old.json` | spec hash, commit, CPU model | docs/a.md |" in page and "3 pages" in page


def test_the_audit_page_is_current(audit) -> None:
    expected = audit.render(audit.audit())
    assert (ROOT / "docs" / "provenance.md").read_text() == expected, "run: python benchmarks/provenance_audit.py --write"


def test_a_commit_a_record_names_must_be_in_the_history(audit, tmp_path) -> None:
    def git(*args: str) -> str:
        done = subprocess.run(["git", "-C", str(tmp_path), *args], capture_output=True, text=True, check=True)
        return done.stdout.strip()

    git("init", "-q")
    (tmp_path / "a.txt").write_text("a\n")
    git("add", "a.txt")
    git("-c", "user.name=t", "-c", "user.email=t@t", "commit", "-q", "-m", "a")
    head = git("rev-parse", "HEAD")
    results = tmp_path / "benchmarks" / "results"
    results.mkdir(parents=True)
    (results / "good.json").write_text(json.dumps({"machine": {"commit": head}, "runs": [{"commit": head[:7]}]}))
    (results / "dirty.json").write_text(json.dumps({"commit": head[:10] + "+uncommitted changes"}))
    (results / "rebased.json").write_text(json.dumps({"runs": [{"provenance": {"commit": "0123abc"}}, {"commit": "unknown"}]}))
    assert audit.commits_outside_history(tmp_path) == {"rebased.json": ["0123abc"]}
    (tmp_path / ".git").rename(tmp_path / "not-git")
    assert audit.commits_outside_history(tmp_path) is None


def test_every_commit_a_record_names_is_in_this_history(audit) -> None:
    found = audit.commits_outside_history()
    if found is None:
        pytest.skip("not a full git clone: the history cannot say which commits exist")
    assert found == {}, f"records naming commits outside this history (made on a rebased branch?): {found}"
