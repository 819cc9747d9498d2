"""Studies as specs: parsing, planning, running (local and Ray), records, statistics, registration, reports."""

from __future__ import annotations

import hashlib
import json
import math
import os
import re
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest

from pimbrl.cli import main
from pimbrl.config import ConfigError
from pimbrl.experiments import stats
from pimbrl.experiments.engine import RECORD_FILE, collect_record, plan_study, run_study
from pimbrl.experiments.registration import start_study, study_label
from pimbrl.experiments.report import load_record, study_report
from pimbrl.experiments.spec import load_spec, parse_spec
from pimbrl.training import resolve_config
from pimbrl.training.rundir import cpu_model
from tests.test_external import needs_controlgym  # a study of controlgym's systems imports it: `.ci/run` runs those

#: a run of a few seconds (Pendulum, MFRL or a two-step model fit)
TINY = {
    "total_steps": 80,
    "warmup_steps": 20,
    "update_after": 20,
    "eval_every": 40,
    "eval_episodes": 1,
    "agent.hidden": [32, 32],
    "agent.batch_size": 32,
    "model.start_after": 20,
    "fit.steps": 1,
    "check.threshold": 1e3,
}

#: the settings of TINY an MFRL run has
TINY_MFRL = {k: v for k, v in TINY.items() if not k.startswith(("fit.", "model.", "check."))}


def _spec(tmp_path: Path, name: str = "s.yaml", **data) -> Path:
    body = {"systems": ["pendulum"], "methods": ["mfrl"], "seeds": [0], "overrides": TINY_MFRL, **data}
    path = tmp_path / name
    path.write_text(json.dumps(body))  # JSON is YAML
    return path


# ---------------------------------------------------------------------------------- the spec
def test_a_spec_is_checked_when_read_and_identified_by_its_bytes(tmp_path) -> None:
    path = _spec(tmp_path, methods={"mfrl": {}, "mbrl": {"overrides": {"fit.steps": 2}}}, seeds=3, thresholds=[-200])
    spec = load_spec(path)
    assert spec.sha256 == hashlib.sha256(path.read_bytes()).hexdigest()
    assert spec.seeds == (0, 1, 2) and spec.arm_names == ("mfrl", "mbrl") and spec.arm("mbrl").overrides == {"fit.steps": 2}
    assert spec.name == "s" and spec.kind == "exploratory" and spec.thresholds == (-200.0,)
    bad = {
        "colour": "unknown key 'colour'",
        "methods": "unknown method 'pimbr'",
        "seeds": "seed 1 is given twice",
        "hypotheses": "'better' 'sac' is not an arm",
        "kind": "'kind' must be one of exploratory, confirmatory",
        "grid": "'seed' cannot be a grid key",
        "statistics": "confidence must be in",
    }
    values = {
        "colour": "red",
        "methods": ["pimbr"],
        "seeds": [1, 1],
        "hypotheses": {"H1": {"claim": "x", "better": "sac", "than": "mfrl"}},
        "kind": "final",
        "grid": {"seed": [1, 2]},
        "statistics": {"confidence": 1.5},
    }
    for key, message in bad.items():
        with pytest.raises(ConfigError, match=message) as err:
            load_spec(_spec(tmp_path, **{key: values[key]}))
        assert str(tmp_path / "s.yaml") in str(err.value) and "\n" not in str(err.value)
    (tmp_path / "broken.yaml").write_text("systems: [pendulum\n")
    with pytest.raises(ConfigError, match="not valid YAML"):
        load_spec(tmp_path / "broken.yaml")


def test_a_huge_study_is_refused_when_read(tmp_path) -> None:
    with pytest.raises(ConfigError, match="more than a study gives an arm"):
        load_spec(_spec(tmp_path, seeds=list(range(10_001))))
    started = time.monotonic()
    with pytest.raises(ConfigError, match="more than a study plans"):
        load_spec(_spec(tmp_path, seeds=10_000, methods=["mfrl", "mbrl"], grid={"utd": [1, 2, 3, 4, 5, 6]}))
    assert time.monotonic() - started < 5


# ---------------------------------------------------------------------------------- planning
def test_planning_resolves_every_run_with_its_arm_and_the_shared_overrides(tmp_path) -> None:
    spec = load_spec(
        _spec(
            tmp_path,
            methods={"mfrl": {}, "mfrl-matched": {}, "pimbrl-w0": {"method": "pimbrl", "overrides": {"physics.weight": 0.0}}},
            seeds=[0, 2],
            overrides=TINY,
        )
    )
    runs = plan_study(spec, tmp_path / "root")
    assert [(r.arm, r.seed) for r in runs] == [(a, s) for a in ("mfrl", "mfrl-matched", "pimbrl-w0") for s in (0, 2)]
    assert runs[0].path == tmp_path / "root" / "mfrl" / "seed0"  # one system, no grid: ARM/seedK
    by_arm = {r.arm: r.config for r in runs if r.seed == 2}
    assert by_arm["mfrl"] == resolve_config("pimbrl/Pendulum-v0", {**TINY_MFRL, "method": "mfrl", "seed": 2})
    assert by_arm["mfrl-matched"].utd == resolve_config("pimbrl/Pendulum-v0", {"method": "pimbrl"}).utd != by_arm["mfrl"].utd
    assert by_arm["pimbrl-w0"].method.physics.weight == 0.0 and by_arm["pimbrl-w0"].method.fit.steps == 1


def test_planning_refuses_duplicates_unused_overrides_and_stays_inside_its_root(tmp_path) -> None:
    for duplicate in ({"grid": {"utd": [1, 1.0]}}, {"systems": ["pendulum", "pimbrl/Pendulum-v0"]}):
        with pytest.raises(ConfigError, match="is the same run as"):
            plan_study(load_spec(_spec(tmp_path, **duplicate)), tmp_path / "root")
    with pytest.raises(ConfigError, match=r"physics\.weight"):  # applies to no arm
        plan_study(load_spec(_spec(tmp_path, overrides={**TINY, "physics.weight": 0.5})), tmp_path / "root")
    (run,) = plan_study(load_spec(_spec(tmp_path, grid={"env_kwargs": [{"observation": "x/../../../y"}]})), tmp_path / "root")
    assert (tmp_path / "root") in run.path.parents and ".." not in run.path.parts
    with pytest.raises(ConfigError, match="nu must be a finite number"):
        plan_study(load_spec(_spec(tmp_path, systems=["burgers"], overrides={"env_kwargs": {"nu": 1e300}})), tmp_path / "r")
    assert not (tmp_path / "r").exists()


# ---------------------------------------------------------------------------------- running and records
@pytest.mark.slow
def test_a_study_runs_resumably_and_its_record_carries_provenance(tmp_path) -> None:
    spec = load_spec(
        _spec(tmp_path, methods=["mfrl", "mbrl"], seeds=2, comparisons=[["mbrl", "mfrl"]], thresholds=[-1500], overrides=TINY)
    )
    lines: list[str] = []
    record = run_study(spec, tmp_path / "root", jobs=2, status=False, log=lines.append)
    assert record == json.loads((tmp_path / "root" / RECORD_FILE).read_text()) | {"failed": []}
    assert record["spec_sha256"] == spec.sha256 and record["spec"] == spec.text and not record["failed"]
    assert record["provenance"]["cpu"] == cpu_model() != "x86_64"
    assert (tmp_path / "root" / "study.yaml").read_text() == spec.text
    assert len(record["runs"]) == 4 and not record["missing"]
    for run in record["runs"]:
        assert run["provenance"]["cpu"] == cpu_model() and run["provenance"]["cores"] >= 1
        assert run["real_transitions"] == run["steps"] == 80 and run["finished"]
        assert run["curve"]["step"] == [40, 80] and len(run["curve"]["wall_s"]) == 2
        assert run["final_return"] == run["curve"]["return_mean"][-1]
        assert run["updates"] > 0 and run["wall_s"] > 0
        if run["arm"] == "mbrl":
            assert run["imagined_transitions"] > 0 and run["scheme_transitions"] == 0
        else:
            assert run["imagined_transitions"] == 0
    again: list[str] = []
    files = {name: (tmp_path / "root" / name).read_bytes() for name in (RECORD_FILE, "study.json")}
    second = run_study(spec, tmp_path / "root", status=False, log=again.append)  # finished runs are not run again
    assert any("4 runs, 4 finished, 0 to run" in line for line in again) and not any(line.startswith("start") for line in again)
    assert [r["final_return"] for r in second["runs"]] == [r["final_return"] for r in record["runs"]]
    # nothing trained, nothing started: the record (its collection's time and commit) and the starts stay as they were
    assert {name: (tmp_path / "root" / name).read_bytes() for name in files} == files
    (tmp_path / "root" / RECORD_FILE).write_text("{}")  # a record that differs is written again
    run_study(spec, tmp_path / "root", status=False, log=again.append)
    assert json.loads((tmp_path / "root" / RECORD_FILE).read_text())["runs"] == json.loads(files[RECORD_FILE])["runs"]
    assert spec.path is not None
    spec.path.write_text(spec.text + "# edited after its runs\n")  # another spec: its start is recorded, and its record
    edited = load_spec(spec.path)
    run_study(edited, tmp_path / "root", status=False, log=again.append)
    seen = json.loads((tmp_path / "root" / "study.json").read_text())["spec_sha256_seen"]
    assert seen == [spec.sha256, edited.sha256]
    assert json.loads((tmp_path / "root" / RECORD_FILE).read_text())["spec_sha256"] == edited.sha256
    report = study_report(spec, record, figures_dir=tmp_path / "fig", link_base=tmp_path)
    group = report.stats["groups"]["pimbrl/Pendulum-v0 default"]
    assert group["arms"]["mfrl"]["mean"]["value"] == pytest.approx(
        sum(r["final_return"] for r in record["runs"] if r["arm"] == "mfrl") / 2
    )
    assert "mbrl vs mfrl" in group["comparisons"] and len(report.figures) == 2 and all(f.exists() for f in report.figures)
    assert report.figures[1].name.endswith("_profile.png") and "performance profile" in report.markdown
    assert "| mfrl | 2 |" in report.markdown and "(exploratory)" in report.markdown
    assert "fewer than 5 runs per arm" not in report.markdown  # no hypotheses in this spec


def test_a_run_directory_of_another_study_is_refused(tmp_path) -> None:
    (tmp_path / "root").mkdir()
    start_study(load_spec(_spec(tmp_path, name="a.yaml")), tmp_path / "root")
    with pytest.raises(ConfigError, match="holds the study 'a', not 'b'"):
        start_study(load_spec(_spec(tmp_path, name="b.yaml")), tmp_path / "root")


def test_the_watchdog_ends_a_killed_drivers_helpers(tmp_path) -> None:
    """Ray's helpers live in sessions of their own; SIGKILL on the driver must not leave them running."""
    pid_file = tmp_path / "helper.pid"
    driver = textwrap.dedent(
        f"""
        import subprocess, sys, time
        from pimbrl.experiments.watchdog import watch_descendants
        watch_descendants()
        # a helper in a session of its own, which starts one more process (like a raylet and its worker)
        helper = subprocess.Popen([sys.executable, "-c",
            "import subprocess, sys, time; p = subprocess.Popen([sys.executable, '-c', 'import time; time.sleep(300)']);"
            "open({str(pid_file)!r}, 'w').write(f'{{p.pid}}'); time.sleep(300)"], start_new_session=True)
        time.sleep(300)
        """
    )
    proc = subprocess.Popen([sys.executable, "-c", driver])
    try:
        deadline = time.monotonic() + 60
        while not pid_file.exists() or not pid_file.read_text():
            assert time.monotonic() < deadline, "the helper did not start"
            time.sleep(0.1)
        grandchild = int(pid_file.read_text())
        time.sleep(1.0)  # the watchdog has looked at the tree since
        os.kill(grandchild, 0)  # alive while the driver lives
        proc.send_signal(signal.SIGKILL)
        proc.wait()
        deadline = time.monotonic() + 20
        while Path(f"/proc/{grandchild}").exists() and _state(grandchild) != "Z":
            assert time.monotonic() < deadline, "the helper outlived the killed driver"
            time.sleep(0.1)
    finally:
        if proc.poll() is None:
            proc.kill()


def _state(pid: int) -> str:
    try:
        text = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return "gone"
    return text[text.rfind(")") + 2]


# ---------------------------------------------------------------------------------- statistics
def test_censored_medians_and_the_probability_of_improvement() -> None:
    assert stats.censored_median([10, 20, 30], [100] * 3) == {"median": 20.0, "above": None, "at_most": None}
    assert stats.censored_median([10, None, None], [100] * 3) == {"median": None, "above": 100.0, "at_most": None}
    assert stats.censored_median([10, 20, None, None], [100] * 4) == {"median": None, "above": 60.0, "at_most": None}
    assert stats.censored_median([10, 20, 30, None], [100] * 4) == {"median": 25.0, "above": None, "at_most": None}
    # a run stopped early (budget 50) that never reached it: the median is bounded on both sides
    assert stats.censored_median([10, 90, None, 5], [100, 100, 50, 100]) == {"median": None, "above": 30.0, "at_most": 50.0}
    assert stats.median_text(stats.censored_median([10, 90, None, 5], [100, 100, 50, 100])) == "> 30 and <= 50"
    faster = stats.probability_of_improvement(stats.steps_scores([10, 20, 30]), stats.steps_scores([None, None, 40]), reps=500)
    assert faster.value == 1.0 and stats.verdict(faster, (3, 3)) == "inconclusive (fewer than 5 runs per arm)"
    one = stats.probability_of_improvement([1.0], [0.0], reps=500)  # perfectly separated: the interval is [1, 1]
    assert (one.low, one.high) == (1.0, 1.0) and stats.verdict(one, (1, 1)).startswith("inconclusive")
    tied = stats.probability_of_improvement([1.0, 2.0, 3.0], [1.0, 2.0, 3.0], reps=500)
    assert tied.value == 0.5 and stats.verdict(tied) == "inconclusive"
    never = stats.probability_of_improvement(stats.steps_scores([None] * 6), stats.steps_scores([None] * 6), reps=500)
    assert (never.low, never.high) == (0.5, 0.5) and stats.verdict(never, (6, 6)) == "inconclusive"
    # a run stopped at 100 steps cannot rank below one that reached the threshold at 6,000
    assert not stats.comparable_steps([5000, 6000], [9000, 9000], [None, None], [100, 9000])
    assert stats.comparable_steps([5000, 6000], [9000, 9000], [None, None], [9000, 9000])
    worse = stats.probability_of_improvement([0.0] * 10, [1.0] * 10, reps=500)
    assert worse.value == 0.0 and worse.high < 0.5 and stats.verdict(worse, (10, 10)) == "not supported"
    better = stats.probability_of_improvement([1.0 + i for i in range(10)], [-1.0 - i for i in range(10)], reps=500)
    assert better.low > 0.5 and stats.verdict(better, (10, 10)) == "supported"


def test_intervals_are_reproducible_and_contain_their_estimate() -> None:
    values = [-10.0, -12.0, -9.0, -30.0, -11.0]
    a = stats.iqm_interval(values, reps=1000, seed=3)
    assert a == stats.iqm_interval(values, reps=1000, seed=3)
    assert a.low <= a.value <= a.high and a.value == pytest.approx(stats.iqm(values)) and a.n == 5
    assert a.value == pytest.approx((-10.0 - 12.0 - 11.0) / 3)  # 25 % trimmed at each end of 5: the middle three
    m = stats.mean_interval(values, reps=1000)
    assert m.value == pytest.approx(sum(values) / 5) and m.low < m.value < m.high
    d = stats.paired_difference({0: 1.0, 1: 2.0, 5: 9.0}, {0: 0.0, 1: 1.0, 2: 7.0}, reps=500)
    assert d.value == 1.0 and d.n == 2  # seeds both ran: 0 and 1
    assert stats.mean_interval([]).text() == "—" and stats.mean_interval([4.0]).text() == "4.00 [4.00, 4.00]"
    assert math.isnan(stats.probability_of_improvement([], [1.0]).value)


def _rliable_interval(
    scores: list[np.ndarray], func, reps: int, seed: int, confidence: float = 0.95
) -> tuple[float, float, float]:
    """rliable's own stratified-bootstrap estimate, the way this project called it before it was vectorised."""
    import warnings

    from rliable import library

    saved = np.random.get_state()
    np.random.seed(seed)  # rliable draws its resamples from the global generator
    try:
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", category=FutureWarning)
            point, interval = library.get_interval_estimates(
                {"x": [s.reshape(-1, 1) for s in scores] if len(scores) > 1 else scores[0].reshape(-1, 1)},
                lambda *a: np.array([func(*a)]),
                reps=reps,
                confidence_interval_size=confidence,
                random_state=np.random.RandomState(seed),
            )
    finally:
        np.random.set_state(saved)
    return float(point["x"][0]), float(interval["x"][0, 0]), float(interval["x"][1, 0])


@pytest.mark.slow
def test_vectorised_intervals_are_rliables_to_the_last_bit() -> None:
    """The vectorised bootstrap draws rliable's resamples and computes its statistics: every number is identical."""
    from rliable import metrics

    rng = np.random.default_rng(7)
    for case in range(6):
        n, m = int(rng.integers(2, 11)), int(rng.integers(2, 11))
        x = np.round(rng.normal(size=n) * 10, case % 3)  # rounded: ties, as steps to a threshold have
        y = np.round(rng.normal(size=m) * 10, case % 3)
        if case % 2:
            x[: n // 3] = -np.inf  # censored runs (stats.steps_scores)
        seed = case
        finite = x[np.isfinite(x)] if len(x[np.isfinite(x)]) > 1 else y
        got = stats.iqm_interval(finite, reps=300, seed=seed)
        assert (got.value, got.low, got.high) == _rliable_interval([finite], metrics.aggregate_iqm, 300, seed)
        got = stats.mean_interval(y, confidence=0.9, reps=300, seed=seed)
        assert (got.value, got.low, got.high) == _rliable_interval([y], np.mean, 300, seed, confidence=0.9)
        got = stats.probability_of_improvement(x, y, reps=300, seed=seed)
        ranked = stats._ranked(x, y)
        assert (got.value, got.low, got.high) == _rliable_interval(list(ranked), metrics.probability_of_improvement, 300, seed)
    for seed, n in ((11, 10), (12, 3)):  # as many runs in both arms: both arrays' resamples come from one draw
        x, y = np.round(rng.normal(size=n) * 10, 1), np.round(rng.normal(size=n) * 10, 1)
        got = stats.probability_of_improvement(x, y, reps=300, seed=seed)
        ranked = stats._ranked(x, y)
        assert (got.value, got.low, got.high) == _rliable_interval(list(ranked), metrics.probability_of_improvement, 300, seed)
    big_x, big_y = np.round(rng.normal(size=(7, 1500)), 1), np.round(rng.normal(size=(7, 2000)), 1)  # chunks 3, 3, 1
    whole = [np.mean(a[:, None] > b[None, :]) + 0.5 * np.mean(a[:, None] == b[None, :]) for a, b in zip(big_x, big_y)]
    assert stats._improvements(big_x, big_y) == pytest.approx(whole, abs=1e-12)
    assert math.isnan(stats.probability_of_improvement([1.0, math.nan], [0.0, 3.0]).value)  # no number: no estimate
    assert math.isnan(stats.iqm_interval([1.0, math.nan, 2.0, 5.0]).value)
    with pytest.raises(ValueError, match="strictly between 0 and 1"):
        stats.mean_interval([1.0, 2.0], confidence=1.0)
    state = np.random.get_state()[1].copy()
    stats.probability_of_improvement([1.0, 2.0], [0.0, 3.0], reps=50)
    assert (np.random.get_state()[1] == state).all()  # the caller's global generator is left as it was


@pytest.mark.slow
def test_a_report_never_reads_the_best_evaluation(tmp_path) -> None:
    spec = load_spec(_spec(tmp_path, methods=["mfrl", "mbrl"], seeds=2, comparisons=[["mbrl", "mfrl"]]))
    runs = []
    for arm, base in (("mfrl", -900.0), ("mbrl", -700.0)):
        for seed in (0, 1):
            curve = {
                "step": [40, 80],
                "return_mean": [base + seed, base - 50.0 + seed],
                "return_min": [0, 0],
                "return_max": [0, 0],
            }
            runs.append(
                {
                    "system": "pimbrl/Pendulum-v0",
                    "arm": arm,
                    "setting": "default",
                    "seed": seed,
                    "finished": True,
                    "steps": 80,
                    "final_return": base - 50.0 + seed,
                    "best_return": 0.0,
                    "curve": curve,
                }
            )
    record = {"runs": runs, "thresholds": {"pimbrl/Pendulum-v0": [-800.0]}, "spec_sha256": spec.sha256}
    report = study_report(spec, record)
    arms = report.stats["groups"]["pimbrl/Pendulum-v0 default"]["arms"]
    assert arms["mbrl"]["mean"]["value"] == pytest.approx(-749.5) and arms["mfrl"]["mean"]["value"] == pytest.approx(-949.5)
    assert arms["mbrl"]["thresholds"]["-800"]["reached"] == 2 and arms["mfrl"]["thresholds"]["-800"]["reached"] == 0
    assert arms["mbrl"]["thresholds"]["-800"]["median"]["median"] == 40.0
    comparison = report.stats["groups"]["pimbrl/Pendulum-v0 default"]["comparisons"]["mbrl vs mfrl"]
    assert comparison["outcome_poi"]["value"] == 1.0 and comparison["outcome_difference"]["value"] == pytest.approx(200.0)
    assert "CPU: not recorded; commit: not recorded." in report.markdown  # no run names its machine
    for k, run in enumerate(runs[:3]):  # three of four runs name their CPU model and commit
        run["provenance"] = {"cpu": "Some CPU", "commit": f"{k}" * 40}
    runs[0]["provenance"]["cpu_id"] = "GenuineIntel family 6 model 1 stepping 2, flags 0badf00d"
    text = study_report(spec, record).markdown
    assert (
        "CPU: Some CPU (GenuineIntel family 6 model 1 stepping 2, flags 0badf00d) (not recorded for 1 of 4 runs); "
        "commit: 0000000000, 1111111111, 2222222222 (not recorded for 1 of 4 runs)."
    ) in text
    runs[1]["provenance"]["cpu_id"] = "AuthenticAMD family 25 model 1 stepping 1, flags ecfefe0f"
    text = study_report(spec, record).markdown  # two machines: the ids never split the line's fields
    line = next(line for line in text.splitlines() if line.startswith("- **Runs**"))
    assert line.split("; ")[1] == (
        "CPU: Some CPU (AuthenticAMD family 25 model 1 stepping 1, flags ecfefe0f / GenuineIntel family 6 model 1 stepping 2, "
        "flags 0badf00d) (not recorded for 1 of 4 runs)"
    )
    runs[1]["provenance"].pop("cpu_id")
    assert "made under another version" not in text
    record["spec_sha256"] = "f" * 64  # the spec file changed after the record was made: the report says so
    text = study_report(spec, record).markdown
    assert (
        f"SHA-256 `{spec.sha256[:16]}`; **the record was made under another version of it**, SHA-256 `ffffffffffffffff`" in text
    )


# ---------------------------------------------------------------------------------- registration
def _git(repo: Path, *args: str) -> None:
    env = {
        **os.environ,
        "GIT_AUTHOR_NAME": "t",
        "GIT_AUTHOR_EMAIL": "t@t",
        "GIT_COMMITTER_NAME": "t",
        "GIT_COMMITTER_EMAIL": "t@t",
    }
    subprocess.run(["git", "-C", str(repo), *args], check=True, capture_output=True, env=env)


def test_a_confirmatory_spec_must_be_committed_and_unchanged(tmp_path) -> None:
    repo = tmp_path / "repo"
    repo.mkdir()
    _git(repo, "init", "-q")
    path = _spec(repo, name="c.yaml", kind="confirmatory")
    spec = load_spec(path)
    with pytest.raises(ConfigError, match="is not registered"):
        start_study(spec, tmp_path / "run")
    _git(repo, "add", "c.yaml")
    time.sleep(1.1)  # commit times are whole seconds: the first start comes after the commit
    _git(repo, "commit", "-q", "-m", "register")
    time.sleep(1.1)
    (tmp_path / "run").mkdir()
    registration = start_study(spec, tmp_path / "run")
    assert registration["registered"]["commit"] and registration["spec_sha256"] == spec.sha256
    record = {"registration": registration, "spec_sha256": spec.sha256}
    assert study_label(spec, record)[0] == "confirmatory"
    path.write_text(path.read_text().replace('"seeds": [0]', '"seeds": [0, 1]'))  # changed after the first run started
    changed = load_spec(path)
    assert study_label(changed, record) == (
        "exploratory",
        "the spec changed after its first run started (its SHA-256 differs from the registered one)",
    )
    later = start_study(changed, tmp_path / "run")  # a later start with the changed spec is recorded too
    assert study_label(spec, {"registration": later, "spec_sha256": spec.sha256})[0] == "exploratory"
    assert study_label(load_spec(_spec(tmp_path)), {})[0] == "exploratory"


def test_a_record_s_imported_files_are_judged_by_their_bytes_not_the_folder_they_were_read_from(tmp_path) -> None:
    """A confirmatory record reported from another clone keeps its label; an imported file that changed loses it."""
    import hashlib

    system = tmp_path / "my_system.py"
    system.write_text("# a user's system\n")
    path = _spec(tmp_path, kind="confirmatory", imports=["my_system.py"], record={"path": "r.json", "format": "study"})
    spec = load_spec(path)
    digest = hashlib.sha256(system.read_bytes()).hexdigest()
    registration = {
        "spec_sha256": spec.sha256,
        "first_run_started_unix": 2.0,
        "registered": {"commit": "0" * 40, "committed_unix": 1.0},
        "imports_sha256": {"/elsewhere/clone/my_system.py": digest},  # the clone the study ran in
    }
    record = {"registration": registration, "spec_sha256": spec.sha256, "runs": []}
    assert study_label(spec, record)[0] == "confirmatory"
    for other in ({}, {"a.py": digest, "b.py": digest}, None, [digest]):  # fewer, more or malformed imports
        assert study_label(spec, {**record, "registration": {**registration, "imports_sha256": other}})[0] == "exploratory"
    system.write_text("# a user's system, edited after the runs\n")
    assert study_label(spec, record) == (
        "exploratory",
        "a file the spec imports (a system's code) changed after the first run started",
    )


def test_a_confirmatory_study_s_status_lines_leave_the_returns_out(tmp_path, monkeypatch) -> None:
    """The driver's lines of a confirmatory study show steps, not returns; an exploratory study's show both."""
    import pimbrl.experiments.engine as engine
    import pimbrl.experiments.registration as registration

    seen: list[bool] = []

    def run_all(specs, **kw):  # the study opens (its runs are not trained) and ends as its runs stand
        seen.append(kw["returns"])
        while kw["more"]():
            pass
        return []

    monkeypatch.setattr(engine, "run_all", run_all)
    monkeypatch.setattr(registration, "start_study", lambda *a, **kw: {})
    monkeypatch.setattr(registration, "check_start", lambda *a, **kw: (None, None))
    for kind in ("confirmatory", "exploratory"):
        engine.run_study(load_spec(_spec(tmp_path, name=f"{kind}.yaml", kind=kind)), tmp_path / kind, log=lambda line: None)
    assert seen == [False, True]


@pytest.mark.slow
def test_the_pages_put_confirmatory_studies_and_their_verdicts_first_and_name_those_still_running(tmp_path, monkeypatch) -> None:
    from pimbrl.experiments.report import write_pages

    repo = tmp_path / "repo"
    (repo / "benchmarks" / "confirmatory").mkdir(parents=True)
    _git(repo, "init", "-q")
    hypotheses = {"H 1": {"claim": "mbrl beats mfrl", "better": "mbrl", "than": "mfrl"}}
    body = {"kind": "confirmatory", "methods": ["mfrl", "mbrl"], "seeds": [0, 1, 2, 3, 4], "hypotheses": hypotheses,
            "record": {"path": "done.json", "format": "study"}}  # fmt: skip
    done = _spec(repo / "benchmarks" / "confirmatory", name="done.yaml", **body)
    running = _spec(
        repo / "benchmarks" / "confirmatory", name="running.yaml", **{**body, "record": {"path": "r.json", "format": "study"}}
    )
    explored = _spec(repo, name="explored.yaml", record={"path": "explored.json", "format": "study"})
    _git(repo, "add", ".")
    time.sleep(1.1)  # commit times are whole seconds: the first start comes after the commit
    _git(repo, "commit", "-q", "-m", "register")
    time.sleep(1.1)
    spec = load_spec(done)
    (tmp_path / "run").mkdir()
    registration = start_study(spec, tmp_path / "run")
    runs = [{"system": "pimbrl/Pendulum-v0", "arm": arm, "setting": "default", "seed": seed, "finished": True, "steps": 80,
             "final_return": base + seed, "curve": {"step": [80], "return_mean": [base + seed], "return_min": [0], "return_max": [0]}}
            for arm, base in (("mfrl", -900.0), ("mbrl", -700.0)) for seed in range(5)]  # fmt: skip
    record = {"runs": runs, "thresholds": {}, "spec_sha256": spec.sha256, "registration": registration}
    (done.parent / "done.json").write_text(json.dumps(record))
    (repo / "explored.json").write_text(json.dumps({**record, "registration": None}))
    docs = repo / "docs"
    monkeypatch.chdir(repo)  # the commands name each spec as seen from where the pages are made (the repository)
    write_pages([load_spec(explored), spec, load_spec(running)], docs)
    page = (docs / "results.md").read_text()
    assert page.index("## done (confirmatory)") < page.index("## explored (exploratory)")  # confirmatory first
    assert "Confirmatory studies: [done](#done-confirmatory); confirmatory specs without a record yet: running." in page
    row = "| [done](#done-confirmatory) | H 1 | mbrl beats mfrl | Pendulum-v0 | final return | 1.00 [1.00, 1.00] (95%) | supported |"
    assert row in page  # an id with a space is still the id
    assert "- **Command**: `pimbrl study run benchmarks/confirmatory/done.yaml && pimbrl study report" in page
    reproduce = (docs / "reproduce.md").read_text()
    assert "`pimbrl study run benchmarks/confirmatory/done.yaml --run-dir runs/done`" in reproduce
    assert "| running | confirmatory spec, no record yet | `pimbrl study run benchmarks/confirmatory/running.yaml" in reproduce
    done.write_text(done.read_text().replace('"seeds": [0, 1, 2, 3, 4]', '"seeds": [4, 3, 2, 1, 0]'))  # changed: demoted
    write_pages([load_spec(explored), load_spec(done)], docs)
    page = (docs / "results.md").read_text()
    assert "Confirmatory studies: none with a record yet; confirmatory specs whose record is exploratory: " in page
    assert "[done](#done-exploratory) (the spec changed after its first run started" in page
    assert "| H 1 |" not in page.split("Studies:")[0]  # no verdict table for a demoted study
    (repo / "explored.json").unlink()
    with pytest.raises(FileNotFoundError, match="study explored: its record"):  # only a confirmatory one may wait
        write_pages([load_spec(explored)], docs)


# ---------------------------------------------------------------------------------- the command line and compare
@pytest.mark.slow
def test_study_commands_plan_run_and_report(tmp_path, capsys) -> None:
    path = _spec(tmp_path, methods=["mfrl"], seeds=2, hypotheses={"H1": {"claim": "c", "better": "mfrl", "than": "mfrl"}})
    root = tmp_path / "root"
    assert main(["study", "plan", str(path), "--run-dir", str(root)]) == 0
    assert "2 runs of study s (exploratory)" in capsys.readouterr().out and not root.exists()
    assert main(["study", "run", str(path), "--run-dir", str(root), "--jobs", "2"]) == 0
    assert main(["study", "report", str(path), "--run-dir", str(root)]) == 0
    out = capsys.readouterr().out
    assert "## s (exploratory)" in out and (root / "report.md").read_text() in out and "| H1 | c |" in out
    _status_reads_states_and_steps_but_no_return(path, root, capsys)
    assert main(["study", "run", str(tmp_path / "missing.yaml")]) == 2
    assert "study spec" in capsys.readouterr().err


def _status_reads_states_and_steps_but_no_return(path: Path, root: Path, capsys) -> None:
    import shutil

    from pimbrl.experiments.progress import study_progress
    from pimbrl.training.rundir import RunDirectory

    spec = load_spec(path)
    returns = [RunDirectory(root / "mfrl" / f"seed{k}").result()["final_return"] for k in (0, 1)]
    assert main(["study", "status", str(path), "--run-dir", str(root), "--jobs", "2"]) == 0
    out = capsys.readouterr().out
    assert "2 runs; 2 finished, 0 running, 0 interrupted, 0 not started" in out and "| mfrl | 2/2 | 0 | 0 | 0 |" in out
    assert not any(f"{r:.2f}" in out or f"{r:.1f}" in out for r in returns)  # no outcome is shown
    one = RunDirectory(root / "mfrl" / "seed1")
    one.update_status(status="running")  # a process that died mid-run: interrupted
    assert [p.state for p in study_progress(spec, root)] == ["finished", "interrupted"]
    writer = RunDirectory(root / "mfrl" / "seed1")
    writer.lock()  # another writer holds it: running
    try:
        progress = study_progress(spec, root)
        assert progress[1].state == "running" and progress[1].steps == progress[1].total_steps
    finally:
        writer.close()
    shutil.rmtree(root / "mfrl" / "seed0")
    assert main(["study", "status", str(path), "--run-dir", str(root)]) == 0
    out = capsys.readouterr().out
    assert "0 finished, 0 running, 1 interrupted, 1 not started" in out and "which no finished run times yet" in out
    (root / "mfrl" / "seed1" / "config.json").write_text("{not json")  # one damaged run: named, the rest listed
    assert main(["study", "status", str(path), "--run-dir", str(root)]) == 0
    out = capsys.readouterr().out
    assert "0 interrupted, 1 not started, 1 unreadable" in out and f"Unreadable: {root / 'mfrl' / 'seed1'}: " in out


def test_status_times_an_arm_with_no_finished_run_by_another_setting_of_its_method(tmp_path) -> None:
    from pimbrl.experiments.engine import plan_study
    from pimbrl.experiments.progress import QueueTotals, RunProgress, progress_lines

    methods = {"lr-a": {"method": "mfrl", "overrides": {"agent.actor_lr": 1e-3}},
               "lr-b": {"method": "mfrl", "overrides": {"agent.actor_lr": 3e-3}},
               "matched": {"method": "mfrl", "match_updates": True}, "mbrl": {"method": "mbrl"}}  # fmt: skip
    spec = load_spec(_spec(tmp_path, methods=methods, seeds=2))
    runs = plan_study(spec, tmp_path / "root")
    progress = [RunProgress(r, "finished", r.config.total_steps, 120.0) if r.arm == "lr-a" else RunProgress(r, "not started", 0, None)
                for r in runs]  # fmt: skip
    totals = QueueTotals()
    estimate = next(line for line in progress_lines(spec, progress, totals=totals) if line.startswith("Estimate"))
    assert estimate.startswith("Estimate: about 4 CPU-minutes left")  # lr-b's two runs at lr-a's 2 minutes
    assert totals.left_s == 240.0 and totals.untimed == ["s (matched, mbrl)"]  # a queue's total adds the same
    assert "(lr-b timed by the finished runs of the other settings of their method and agent" in estimate
    assert "plus matched, mbrl, which no finished run times yet" in estimate  # other updates per step; another method
    horizons = {
        "h5": {"method": "mpc", "overrides": {"model.horizon": 5}},
        "h9": {"method": "mpc", "overrides": {"model.horizon": 9}},
    }
    spec = load_spec(_spec(tmp_path, name="c.yaml", methods=horizons, seeds=1, overrides={"eval_episodes": 2}))
    runs = plan_study(spec, tmp_path / "c")
    progress = [RunProgress(runs[0], "finished", 0, 600.0), RunProgress(runs[1], "not started", 0, None)]
    estimate = next(line for line in progress_lines(spec, progress, totals=totals) if line.startswith("Estimate"))
    assert "plus h9, which no finished run times yet" in estimate  # a controller's cost follows its horizon
    assert totals.line(2, 2) == (
        "Queue of 2 studies: about 4 CPU-minutes left that finished runs time, 2 minutes at --jobs 2; "
        "not timed yet: s (matched, mbrl); c (h9)."
    )


def test_status_counts_a_dpc_runs_gradient_steps(tmp_path, capsys) -> None:
    """A DPC run has no evaluations while it trains: status reads its gradient steps from control.json."""
    from pimbrl.experiments.engine import plan_study
    from pimbrl.experiments.progress import progress_lines, study_progress
    from pimbrl.training import create_run
    from pimbrl.training.rundir import RunDirectory

    overrides = {"model.iterations": 400, "model.horizon": 3, "eval_episodes": 2}
    spec = load_spec(_spec(tmp_path, methods={"dpc": {"overrides": overrides}}, overrides={}, seeds=2))
    root = tmp_path / "root"
    runs = plan_study(spec, root)
    for run, steps in zip(runs, (100, 300)):
        create_run(run.config, run.path, progress=False).run_dir.close()  # started, then stopped
        (run.path / "control.json").write_text(json.dumps({"dpc": {"steps": steps}, "wall_s": 60.0}))
    writer = RunDirectory(runs[0].path)
    writer.lock()
    try:
        progress = study_progress(spec, root)
        assert [(p.state, p.steps, p.total_steps) for p in progress] == [("running", 100, 400), ("interrupted", 300, 400)]
        text = "\n".join(progress_lines(spec, progress))
        assert "| dpc | 0/2 | 1 (100/400 DPC steps) | 1 | 0 |" in text
    finally:
        writer.close()
    from pimbrl.experiments.runner import RunSpec, child_status

    line = child_status(RunSpec("dpc", runs[0].seed, runs[0].path, runs[0].config))
    assert line == f"dpc seed {runs[0].seed}: 100/400 DPC steps"  # the driver's line, not "starting" throughout
    for damaged in (
        "[1]",
        '{"dpc": [1]}',
        '{"dpc": {"steps": null}}',
        '{"dpc": {"steps": 3}, "wall_s": [2]}',
        "{not json",
        '{"wall_s": "1"}',
    ):
        (runs[1].path / "control.json").write_text(damaged)  # named, not a crash
        assert study_progress(spec, root)[1].state == "unreadable", damaged


@pytest.mark.slow
def test_compare_writes_its_spec_and_the_study_report_reads_it(tmp_path) -> None:
    from pimbrl.experiments.compare import compare

    root = tmp_path / "cmp"
    result = compare("pimbrl/Pendulum-v0", ["mfrl"], [0], root, TINY_MFRL, log=lambda m: None, status=False)
    assert not result["failed"] and (root / "study.yaml").exists() and (root / RECORD_FILE).exists()
    spec = load_spec(root / "study.yaml")
    assert spec.compact and spec.arm_names == ("mfrl",) and spec.systems == ("pimbrl/Pendulum-v0",)
    record = load_record(spec, root)
    assert record["runs"][0]["final_return"] == result["runs"][0]["final_return"]
    assert collect_record(spec, plan_study(spec, root), root)["runs"][0]["path"] == "mfrl/seed0"


def test_a_spec_written_by_a_program_parses_back_to_the_same_study(tmp_path) -> None:
    from pimbrl.experiments.compare import compare_spec

    spec = compare_spec(
        "pimbrl/Burgers-v0", ["mfrl", "pimbrl", "mfrl-matched"], [0, 3], {"physics.sources": ("policy", "box")}, "paper", -11.0
    )
    again = parse_spec(__import__("yaml").safe_load(spec.text), text=spec.text)
    assert again == spec and spec.comparisons == (("pimbrl", "mfrl"), ("pimbrl", "mfrl-matched"))
    assert spec.arm("mfrl-matched").match_updates and spec.overrides == {"physics.sources": ("policy", "box")}


def test_the_example_studies_plan_what_the_partial_physics_driver_ran(tmp_path) -> None:
    """examples/studies/ replaces benchmarks/run_partial_physics.py: each arm is the method it ran."""
    spec = load_spec(Path(__file__).resolve().parents[1] / "examples" / "studies" / "partial_physics_burgers.yaml")
    runs = plan_study(spec, tmp_path)
    assert len(runs) == 18 and {r.config.env_kwargs["nu"] for r in runs} == {0.013}
    by_arm = {r.arm: r.config for r in runs if r.seed == 0}
    assert by_arm["pimbrl-wrong"].method.prior == {"nu": 0.01} and by_arm["pimbrl-true"].method.prior == {}
    assert by_arm["pimbrl-learned"].method.learn.coefficients == {"nu": None}
    assert (
        by_arm["known-scheme-wrong"].method.name == "known-scheme"
        and by_arm["identified-scheme"].method.name == "identified-scheme"
    )


def test_the_generated_pages_cover_every_study_and_links_into_them_resolve() -> None:
    """docs/results.md and docs/reproduce.md are `pimbrl study report --pages` output, one section per spec."""
    import re

    from pimbrl.experiments.report import GENERATED, _anchor

    repo = Path(__file__).resolve().parents[1]
    results = (repo / "docs" / "results.md").read_text()
    reproduce = (repo / "docs" / "reproduce.md").read_text()
    assert results.splitlines()[2] == GENERATED and reproduce.splitlines()[2] == GENERATED
    specs = sorted((repo / "benchmarks" / "studies").glob("*.yaml"))
    for path in sorted((repo / "benchmarks" / "confirmatory").glob("*.yaml")):  # registered: a section once recorded
        spec = load_spec(path)
        if spec.record is not None and spec.record.path.is_file():
            specs.append(path)
        else:  # named as waiting on both pages, so a registered study is never missing from them
            assert f"## {spec.name} (" not in results, f"docs/results.md has {spec.name} but its record is gone"
            waiting = re.search(r"confirmatory specs without a record yet: ([^\n]+?)\. ", results)
            assert waiting and spec.name in waiting.group(1).split(", "), f"docs/results.md omits {spec.name}: regenerate it"
            assert f"| {spec.name} | confirmatory spec, no record yet |" in reproduce, f"docs/reproduce.md omits {spec.name}"
    anchors = set()
    for path in specs:
        spec = load_spec(path)
        heading = re.search(rf"^## {re.escape(spec.name)} \((exploratory|confirmatory)\)$", results, re.M)
        assert heading, f"{spec.name} has no section in docs/results.md: run pimbrl study report --pages"
        assert f"SHA-256 `{spec.sha256[:16]}`" in results, f"docs/results.md has an older {spec.name}: regenerate it"
        anchors.add(_anchor(spec.name, heading.group(1)))
    for page in [repo / "README.md", *sorted((repo / "docs").glob("*.md"))]:
        for anchor in re.findall(r"results\.md#([^)\s]+)\)", page.read_text()):
            assert anchor in anchors, f"{page.name} links to results.md#{anchor}, which is not a study's section"


# ---------------------------------------------------------------------------------- what a report counts (review)
def _fake_runs(arms: dict[str, float], seeds: int, finished: bool = True) -> list[dict]:
    runs = []
    for arm, base in arms.items():
        for seed in range(seeds):
            value = base + seed
            curve = {"step": [40, 80], "return_mean": [value, value], "return_min": [0, 0], "return_max": [0, 0]}
            runs.append({"system": "pimbrl/Pendulum-v0", "arm": arm, "setting": "default", "seed": seed, "finished": finished,
                         "steps": 80, "final_return": value, "curve": curve})  # fmt: skip
    return runs


def test_unfinished_runs_are_left_out_and_make_hypotheses_inconclusive(tmp_path) -> None:
    hypotheses = {"H1": {"claim": "mbrl beats mfrl", "better": "mbrl", "than": "mfrl"}}
    spec = load_spec(_spec(tmp_path, methods=["mfrl", "mbrl"], seeds=6, hypotheses=hypotheses, statistics={"reps": 200}))
    runs = _fake_runs({"mfrl": -900.0, "mbrl": -700.0}, 6)
    record = {"runs": runs, "thresholds": {}, "spec_sha256": spec.sha256}
    assert study_report(spec, record).stats["hypotheses"]["H1 pimbrl/Pendulum-v0 default"]["verdict"] == "supported"
    stopped = {**runs[0], "seed": 6, "final_return": -5000.0, "finished": False}  # a crashed run's last evaluation
    report = study_report(spec, {**record, "runs": [*runs, stopped]})
    arms = report.stats["groups"]["pimbrl/Pendulum-v0 default"]["arms"]
    assert arms["mfrl"]["runs"] == 6 and -5000.0 not in arms["mfrl"]["outcome"].values()
    assert "Unfinished runs, left out of every statistic here: mfrl 1." in report.markdown
    assert report.stats["hypotheses"]["H1 pimbrl/Pendulum-v0 default"]["verdict"] == "inconclusive (runs missing or unfinished)"


@pytest.mark.slow
def test_a_report_leaves_out_runs_of_other_settings(tmp_path) -> None:
    path = _spec(tmp_path)
    record = run_study(load_spec(path), tmp_path / "root", status=False, log=lambda m: None)
    assert len(record["runs"]) == 1
    path.write_text(path.read_text().replace('"agent.batch_size": 32', '"agent.batch_size": 64'))
    changed = load_spec(path)
    again = load_record(changed, tmp_path / "root")
    assert not again["runs"] and "agent.batch_size (32 there, 64 requested)" in again["mismatched"][0]
    assert "Runs left out because their recorded configuration is not the spec's: 1" in study_report(changed, again).markdown


@pytest.mark.slow
def test_a_record_kept_in_the_repository_reports_the_same_twice(tmp_path, capsys) -> None:
    spec_dir = tmp_path / "studies"
    spec_dir.mkdir()
    path = _spec(spec_dir, name="kept.yaml", record={"path": "../results/kept.json", "format": "study"})
    run_study(load_spec(path), tmp_path / "runs", status=False, log=lambda m: None)
    assert (tmp_path / "results" / "kept.json").is_file()
    out_dir = tmp_path / "out"
    for _ in range(2):  # the second call must not read the (run-less) output directory as the study's
        assert main(["study", "report", str(path), "--out", str(out_dir), "--run-dir", str(out_dir)]) == 0
        assert "| mfrl | 1 |" in (out_dir / "report.md").read_text()
    capsys.readouterr()


def test_spec_holes_found_in_review_are_closed(tmp_path) -> None:
    for data, message in (
        ({"methods": ["mfrl", "mfrl"]}, "names an arm twice"),
        ({"methods": {"record.json": {"method": "mfrl"}}}, "not a study file's name"),
    ):
        with pytest.raises(ConfigError, match=message):
            load_spec(_spec(tmp_path, **data))
    (tmp_path / "up.yaml").write_text("name: '..'\nsystems: [pendulum]\nmethods: [mfrl]\nseeds: [0]\n")
    with pytest.raises(ConfigError, match="'name' must be"):
        load_spec(tmp_path / "up.yaml")
    (tmp_path / "nan.yaml").write_text("systems: [pendulum]\nmethods: [mfrl]\nseeds: [0]\nthresholds: [.nan]\n")
    with pytest.raises(ConfigError, match="'thresholds' must be finite numbers"):
        load_spec(tmp_path / "nan.yaml")
    (tmp_path / "twice.yaml").write_text("systems: [pendulum]\nmethods: [mfrl]\nseeds: [0]\nseeds: [0, 1, 2]\n")
    with pytest.raises(ConfigError, match="the key 'seeds' is given twice"):
        load_spec(tmp_path / "twice.yaml")
    clash = {"methods": {"mfrl": {"overrides": {"total_steps": 100}}}, "grid": {"total_steps": [200, 300]}}
    with pytest.raises(ConfigError, match="total_steps is both a grid key and an override of arm mfrl"):
        plan_study(load_spec(_spec(tmp_path, overrides={"eval_episodes": 1}, **clash)), tmp_path / "root")
    assert load_spec(_spec(tmp_path, systems=["burgers"], overrides={}, hypotheses={
        "H": {"claim": "c", "better": "mfrl", "than": "mfrl", "system": "pimbrl/Burgers-v0"}})).hypotheses[0].system  # fmt: skip


def test_a_link_inside_the_study_root_is_refused(tmp_path) -> None:
    spec = load_spec(_spec(tmp_path, methods=["mfrl", "mfrl-matched"]))
    (tmp_path / "root" / "mfrl-matched").mkdir(parents=True)
    (tmp_path / "root" / "mfrl").symlink_to(tmp_path / "root" / "mfrl-matched")  # two arms, one directory
    with pytest.raises(Exception, match="link"):
        run_study(spec, tmp_path / "root", status=False, log=lambda m: None)


def test_registration_refuses_runs_made_before_and_specs_changed_after_their_commit(tmp_path) -> None:
    repo = tmp_path / "repo"
    repo.mkdir()
    _git(repo, "init", "-q")
    path = _spec(repo, name="c.yaml", kind="confirmatory")
    _git(repo, "add", "c.yaml")
    _git(repo, "commit", "-q", "-m", "register")
    spec = load_spec(path)
    runs = plan_study(spec, tmp_path / "old")
    runs[0].path.mkdir(parents=True)
    (runs[0].path / "config.json").write_text("{}")  # a run made before the registration
    with pytest.raises(ConfigError, match="already holds a run made before the study was registered"):
        start_study(spec, tmp_path / "old", runs)
    _git(repo, "update-index", "--assume-unchanged", "c.yaml")  # git status no longer sees edits
    path.write_text(path.read_text().replace('"seeds": [0]', '"seeds": [0, 1]'))
    (tmp_path / "new").mkdir()
    with pytest.raises(ConfigError, match="is not registered"):
        start_study(load_spec(path), tmp_path / "new")
    _git(repo, "update-index", "--no-assume-unchanged", "c.yaml")
    _git(repo, "commit", "-q", "-am", "look, edit, commit again")  # a second commit of the same spec file
    with pytest.raises(ConfigError, match="is not registered"):
        start_study(load_spec(path), tmp_path / "new")


@pytest.mark.slow
def test_the_watchdog_spares_what_the_driver_had_before_it(tmp_path) -> None:
    pid_file = tmp_path / "before.pid"
    driver = textwrap.dedent(
        f"""
        import subprocess, sys, time
        before = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"], start_new_session=True)
        open({str(pid_file)!r}, "w").write(str(before.pid))
        from pimbrl.experiments.watchdog import watch_descendants
        watch_descendants()
        time.sleep(300)
        """
    )
    proc = subprocess.Popen([sys.executable, "-c", driver])
    deadline = time.monotonic() + 60
    while not pid_file.exists() or not pid_file.read_text():
        assert time.monotonic() < deadline
        time.sleep(0.1)
    before = int(pid_file.read_text())
    time.sleep(2.0)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    time.sleep(2.0)  # the watchdog has acted by now
    try:
        assert _state(before) not in ("gone", "Z"), "the watchdog killed a process the driver had before it"
    finally:
        os.kill(before, signal.SIGKILL)


@pytest.mark.slow
def test_a_tuning_report_names_the_rule_s_arms_and_writes_the_choices_as_the_confirmatory_spec_s_arms() -> None:
    """tune-burgers's record, reported: its choices are confirmatory-burgers's arms, entry for entry."""
    import dataclasses

    from pimbrl.config import load_yaml

    repo = Path(__file__).resolve().parents[1]
    spec = dataclasses.replace(load_spec(repo / "benchmarks" / "pending" / "tune-burgers.yaml"), reps=200)
    report = study_report(spec, load_record(spec))
    rules = report.stats["groups"]["pimbrl/Burgers-v0 default"]["tuning_rules"]
    assert rules == {"tuned model-free arm": "mfrl-matched", "best RL arm": "mfrl-matched"}
    assert "the tuned model-free arm is mfrl-matched (-9.767) and the best RL arm is mfrl-matched (-9.767)" in report.markdown
    block = report.markdown.split("```yaml\n")[1].split("```")[0]
    entries = load_yaml(block)  # the project's reader (YAML 1.2 numbers: 1.0e-5 is a number)
    assert set(entries) == set(spec.tuning) and entries["dpc"] == {"method": "dpc", "overrides": {"model.horizon": 40}}
    recipe_block = report.markdown.split("```yaml\n")[2].split("```")[0]
    recipe = load_yaml(recipe_block)  # the best recipe's sections, as src/pimbrl/systems/burgers.yaml holds them
    from pimbrl.systems.presets import load_presets

    best = load_presets(repo / "src" / "pimbrl" / "systems" / "burgers.yaml")[1]["best"]
    assert recipe["methods"] == {k: dict(v) for k, v in best.methods.items()}
    assert recipe["agents"] == {k: dict(v) for k, v in best.agents.items()}


@pytest.mark.slow
@pytest.mark.parametrize(
    ("system", "preset"),
    [(name, f"src/pimbrl/systems/{name}.yaml") for name in ("burgers", "pendulum", "cartpole", "ks")]
    + [("allen-cahn", "examples/allen_cahn.yaml")]
    + [pytest.param("cg-burgers", "benchmarks/controlgym_burgers.yaml", marks=needs_controlgym)],
)
def test_a_best_recipe_holds_its_tuning_report_s_recipe_sections(system: str, preset: str) -> None:
    """The system's preset's `best` (src/pimbrl/systems/SYSTEM.yaml, or the example's) is what tune-SYSTEM's report
    writes, section for section; where its `chosen_by` names later tuning studies that amend tune-SYSTEM (`pimbrl
    study draft TUNING AMENDMENT...`), their entries replace tune-SYSTEM's, method for method."""
    import dataclasses

    from pimbrl.config import load_yaml
    from pimbrl.systems.presets import load_presets

    repo = Path(__file__).resolve().parents[1]
    best = load_presets(repo / preset)[1]["best"]
    assert f"tune-{system}" in best.chosen_by and "validation" in best.chosen_by
    named = (re.sub(r"\.(yaml|json)$", "", t) for t in re.findall(r"\btune-[A-Za-z0-9+.\-]*[A-Za-z0-9+]", best.chosen_by))
    studies = list(dict.fromkeys(named))  # tune-SYSTEM first, then the studies amending it, as chosen_by names them
    assert studies[0] == f"tune-{system}"
    recipe: dict[str, dict] = {"methods": {}, "agents": {}}
    for name in studies:
        spec = dataclasses.replace(load_spec(repo / "benchmarks" / "pending" / f"{name}.yaml"), reps=200)
        report = study_report(spec, load_record(spec))
        sections = load_yaml(report.markdown.split("```yaml\n")[2].split("```")[0])
        for section in recipe:
            recipe[section].update(sections.get(section) or {})
        confirmatory = repo / "benchmarks" / "confirmatory" / f"confirmatory-{system}.yaml"
        steps = load_spec(confirmatory).overrides.get("total_steps") if confirmatory.is_file() else None
        for key, value in spec.overrides.items():  # the budget every candidate ran with is the recipe's
            # a model's setting reaches the methods with a model; any other must reach a model-free run as well
            settings = best.for_method(key.split(".")[0] in ("model", "physics", "imagine", "fit", "check", "finetune"))
            if key == "total_steps" and steps is not None:  # KS tunes shorter runs: the confirmatory length
                assert settings.get(key) == steps, key
            elif key != "eval_protocol":
                assert settings.get(key) == value, key
    assert recipe["methods"] == {k: dict(v) for k, v in best.methods.items()}
    assert recipe["agents"] == {k: dict(v) for k, v in best.agents.items()}


_CONFIRMATORY_SPECS = sorted((Path(__file__).resolve().parents[1] / "benchmarks" / "confirmatory").glob("confirmatory-*.yaml"))


def _imports_controlgym(path: Path) -> bool:
    from pimbrl.config import load_yaml

    return any("controlgym" in str(i) for i in load_yaml(path.read_text()).get("imports") or [])


def _tuning_studies(path: Path) -> list[str]:
    """The tuning studies a registered spec's arms come from: those its draft's comment names (tune-X, then the
    studies amending it, `pimbrl study draft TUNING AMENDMENT...`), else tune-X alone (specs drafted by hand)."""
    found = re.search(r"^  # (.+)'s choices: the highest IQM", path.read_text(), re.MULTILINE)
    return found.group(1).split(" and ") if found else [path.stem.replace("confirmatory-", "tune-", 1)]


def test_a_registered_spec_names_its_tuning_studies_as_its_draft_wrote_them(tmp_path) -> None:
    spec = tmp_path / "confirmatory-x.yaml"
    spec.write_text("methods:\n  # tune-x and tune-x-scheme's choices: the highest IQM of the final validation return\n")
    assert _tuning_studies(spec) == ["tune-x", "tune-x-scheme"]
    spec.write_text("methods:\n  mfrl: {method: mfrl}\n")
    assert _tuning_studies(spec) == ["tune-x"]
    assert _tuning_studies(_CONFIRMATORY_SPECS[0]) == [_CONFIRMATORY_SPECS[0].stem.replace("confirmatory-", "tune-", 1)]


def _waiting_specs() -> list[Path]:
    """The engine specs a queue may still run: benchmarks/pending/ and the registered ones without a record yet."""
    from pimbrl.config import load_yaml

    repo = Path(__file__).resolve().parents[1]
    found = []
    for path in sorted([*(repo / "benchmarks" / "pending").glob("*.yaml"), *_CONFIRMATORY_SPECS]):
        record = load_yaml(path.read_text()).get("record") or {}
        if record.get("format", "study") == "study" and not (path.parent / str(record.get("path", ""))).is_file():
            found.append(path)
    return found


@pytest.mark.parametrize(
    "path", [pytest.param(p, id=p.stem, marks=[needs_controlgym] if _imports_controlgym(p) else []) for p in _waiting_specs()]
)
def test_every_spec_waiting_in_the_queue_plans_every_run(path: Path, tmp_path) -> None:
    """A queued study whose runs cannot be configured would stop the queue hours later: `plan_study` resolves every
    run's configuration now (a setting that applies to no run, or a bad value, raises) and gives each its own folder."""
    spec = load_spec(path)
    runs = plan_study(spec, tmp_path)
    settings = math.prod(len(v) for v in spec.grid.values())
    expected = len(spec.systems) * settings * sum(len(arm.seeds or spec.seeds) for arm in spec.arms)
    assert len(runs) == expected and len({r.path for r in runs}) == len(runs), path.name


@pytest.mark.slow
@pytest.mark.parametrize(
    "path",
    [  # a spec that imports controlgym's adapter needs controlgym, a benchmark-only install
        pytest.param(p, id=p.stem, marks=[needs_controlgym] if _imports_controlgym(p) else []) for p in _CONFIRMATORY_SPECS
    ],
)
def test_every_registered_arm_is_its_tuning_report_s_entry(path: Path) -> None:
    """confirmatory-X's arms are tune-X's choices, entry for entry, as its report writes them."""
    import dataclasses

    from pimbrl.config import load_yaml

    repo = Path(__file__).resolve().parents[1]
    names = _tuning_studies(path)
    assert names[0] == path.stem.replace("confirmatory-", "tune-", 1), f"{path.name} names {names[0]} first"
    entries: dict = {}
    specs = []
    for name in names:  # tune-X's entries, then each amendment's for the methods it tuned again
        tuning = repo / "benchmarks" / "pending" / f"{name}.yaml"
        assert tuning.is_file(), f"{path.name} has no tuning study {tuning.name}"
        specs.append(dataclasses.replace(load_spec(tuning), reps=200))
        report = study_report(specs[-1], load_record(specs[-1]))
        entries.update(load_yaml(report.markdown.split("```yaml\n")[1].split("```")[0]))
    spec = specs[0]  # the study whose overrides the confirmatory spec keeps (an amendment has the same)
    confirmatory = load_spec(path)
    assert {arm.name for arm in confirmatory.arms} <= set(entries), path.name
    for key, value in spec.overrides.items():  # the system as tuned (a wrong prior included), judged on holdout
        if key not in ("eval_protocol", "total_steps"):  # the budget may differ (KS tunes shorter runs)
            assert confirmatory.overrides.get(key) == value, f"{path.name}: {key}"
    for arm in confirmatory.arms:
        entry = entries[arm.name]
        assert (entry["method"], entry.get("match_updates", False)) == (arm.method, arm.match_updates), arm.name
        assert {k: tuple(v) if isinstance(v, list) else v for k, v in entry["overrides"].items()} == arm.overrides, arm.name


def test_steps_hypotheses_also_count_the_imagined_transitions_made_by_the_threshold(tmp_path) -> None:
    hypotheses = {"H3": {"claim": "c", "better": "known-scheme", "than": "mfrl", "metric": "steps_to_threshold",
                         "threshold": -800}}  # fmt: skip
    spec = load_spec(_spec(tmp_path, methods=["mfrl", "known-scheme"], seeds=5, hypotheses=hypotheses,
                           statistics={"reps": 200}))  # fmt: skip
    runs = []
    for seed in range(5):
        curve = {"step": [40, 80], "return_min": [0, 0], "return_max": [0, 0]}
        reached = seed < 4  # seed 4 of known-scheme never reaches -800: censored at 80 + its 300 imagined
        runs.append({"system": "pimbrl/Pendulum-v0", "arm": "known-scheme", "setting": "default", "seed": seed,
                     "finished": True, "steps": 80, "final_return": -700.0, "imagined_transitions": 300,
                     "curve": {**curve, "return_mean": [-700.0 if reached else -900.0] * 2, "imagined_total": [100.0, 300.0]}})  # fmt: skip
        runs.append({"system": "pimbrl/Pendulum-v0", "arm": "mfrl", "setting": "default", "seed": seed, "finished": True,
                     "steps": 80, "final_return": -750.0, "curve": {**curve, "return_mean": [-900.0, -750.0]}})  # fmt: skip
    report = study_report(spec, {"runs": runs, "thresholds": {}, "spec_sha256": spec.sha256})
    counted = report.stats["hypotheses"]["H3 pimbrl/Pendulum-v0 default"]["with_imagined"]
    assert counted["known-scheme"]["real"]["median"] == 40 and counted["known-scheme"]["with_imagined"]["median"] == 140
    assert counted["mfrl"]["real"]["median"] == 80 and counted["mfrl"]["with_imagined"]["median"] == 80
    assert "| H3 | Pendulum-v0 | -800 | known-scheme | 4/5 | 40 | 140 |" in report.markdown
    runs[0]["curve"]["imagined_total"] = [None, 300.0]  # not logged at the evaluation that reached -800
    report = study_report(spec, {"runs": runs, "thresholds": {}, "spec_sha256": spec.sha256})
    assert "Not counted with the imagined transitions: H3 (Pendulum-v0)" in report.markdown
    for run in runs:  # a record made before the curve carried imagined transitions: no such table, no guess
        run["curve"].pop("imagined_total", None)
    report = study_report(spec, {"runs": runs, "thresholds": {}, "spec_sha256": spec.sha256})
    assert "with_imagined" not in report.stats["hypotheses"]["H3 pimbrl/Pendulum-v0 default"]
    assert "real + imagined" not in report.markdown and "Not counted with the imagined transitions: H3" in report.markdown


def test_a_run_s_curve_carries_the_imagined_transitions_made_by_each_evaluation(tmp_path) -> None:
    from pimbrl.training.rundir import RunDirectory

    run = RunDirectory(tmp_path)
    assert run._imagined_at([40, 80]) == {}  # no metrics: a run without them
    (tmp_path / "metrics.csv").write_text("step,wall_s,imagined_total\n40,1.0,\n60,2.0,100\n80,3.0,250\n120,4.0,400\n")
    assert run._imagined_at([40, 80, 100]) == {"imagined_total": [None, 250.0, None]}  # only a row at that very step
    (tmp_path / "metrics.csv").write_text("step,wall_s\n40,1.0\n")
    assert run._imagined_at([40]) == {}  # a model-free run logs none
    (tmp_path / "metrics.csv").write_text("step,wall_s,imagined_total\n40,1.0,nan\n")
    assert run._imagined_at([40]) == {}  # a damaged log: no count, and no error (the outcome does not need it)


def test_status_takes_several_specs_each_from_its_own_directory(tmp_path, capsys, monkeypatch) -> None:
    monkeypatch.chdir(tmp_path)
    a, b = _spec(tmp_path, name="a.yaml"), _spec(tmp_path, name="b.yaml")
    assert main(["study", "status", str(a), str(b)]) == 0
    out = capsys.readouterr().out
    assert "study a: no run directory runs/a yet" in out and "study b: no run directory runs/b yet" in out
    assert out.rstrip().endswith(
        "Queue of 2 studies: about 0 CPU-minutes left that finished runs time, 0 minutes at --jobs 1; not timed yet: "
        "a (no run directory yet); b (no run directory yet)."
    )
    assert main(["study", "status", str(a), str(b), "--run-dir", "x"]) == 2
    assert "own directory and archive: drop --run-dir, --archive" in capsys.readouterr().err
    assert main(["study", "plan", str(a), str(b)]) == 2
    assert "several only with run, status, draft or report --pages" in capsys.readouterr().err


@pytest.mark.slow
def test_a_queue_starts_the_next_study_in_a_process_the_last_one_leaves_free(tmp_path, capsys, monkeypatch) -> None:
    """`pimbrl study run A B --jobs 2`: B's run starts beside A's last, each study gets its own record, and the runs
    are the ones each study makes alone."""
    from pimbrl.experiments.engine import QueuedStudy, run_studies

    a = load_spec(_spec(tmp_path, name="a.yaml"))
    b = load_spec(_spec(tmp_path, name="b.yaml", seeds=[1], overrides={**TINY_MFRL, "total_steps": 400}))  # longer
    lines: list[str] = []
    queue = [QueuedStudy(a, tmp_path / "qa"), QueuedStudy(b, tmp_path / "qb")]
    records = run_studies(queue, jobs=2, status=False, log=lines.append)
    starts = [i for i, line in enumerate(lines) if line.startswith("start ")]
    done = [i for i, line in enumerate(lines) if line.startswith("done ")]
    assert len(starts) == 2 and max(starts) < min(done)  # both at once: a's one run left a process to b
    assert "/qa/" in lines[starts[0]] and "/qb/" in lines[starts[1]]
    recorded = [i for i, line in enumerate(lines) if " runs recorded in " in line]
    assert [lines[i].split(":")[0] for i in recorded] == ["study a", "study b"]
    assert recorded[0] < done[1]  # a's record was written when a's run ended, while b's still trained
    assert [r["study"] for r in records] == ["a", "b"] and all(not r["failed"] for r in records)
    assert json.loads((tmp_path / "qa" / RECORD_FILE).read_text())["runs"][0]["seed"] == 0
    alone = run_study(b, tmp_path / "b-alone", status=False, log=lambda m: None)
    assert alone["runs"][0]["curve"]["return_mean"] == records[1]["runs"][0]["curve"]["return_mean"]
    # the CLI: a queue of finished studies trains nothing and writes both records again
    monkeypatch.chdir(tmp_path)
    for name in ("a", "b"):
        (tmp_path / "runs").mkdir(exist_ok=True)
        os.replace(tmp_path / f"q{name}", tmp_path / "runs" / name)
    assert main(["study", "run", "a.yaml", "b.yaml", "--jobs", "2", "--no-archive"]) == 0
    out = capsys.readouterr().out
    assert "study a: 1 runs, 1 finished, 0 to run" in out and "study b: 1 runs, 1 finished, 0 to run" in out
    assert "study a: 1 runs recorded in" in out and "study b: 1 runs recorded in" in out


@pytest.mark.slow
@pytest.mark.parametrize(
    ("how", "line"),
    [("raise SystemExit('fragile: told to fail')", "FAILED "), ("os.kill(os.getpid(), signal.SIGTERM)", "stopped ")],
    ids=["fails", "stopped"],
)
def test_a_failed_run_is_its_own_study_s_and_the_queue_goes_on(tmp_path, how: str, line: str) -> None:
    """A run that fails, or that a signal sent to it alone stops, is its study's failure; the next study trains."""
    from pimbrl.experiments.engine import QueuedStudy, run_studies

    (tmp_path / "fragile.py").write_text(
        f"import os, signal\nfrom pathlib import Path\nif Path(__file__).with_suffix('.fail').exists():\n    {how}\n"
    )
    a = load_spec(_spec(tmp_path, name="a.yaml", imports=["fragile.py"], seeds=[0, 1]))
    b = load_spec(_spec(tmp_path, name="b.yaml"))
    queue = [QueuedStudy(a, tmp_path / "qa"), QueuedStudy(b, tmp_path / "qb")]  # fragile.py imported here, unharmed
    (tmp_path / "fragile.fail").write_text("")  # each child of a imports it again: each fails
    lines: list[str] = []
    records = run_studies(queue, jobs=2, status=False, log=lines.append)
    assert sorted(records[0]["failed"]) == ["mfrl/seed0", "mfrl/seed1"]  # in its record, relative to its directory
    assert not records[1]["failed"] and records[1]["runs"][0]["final_return"] is not None
    assert sum(entry.startswith(line) for entry in lines) == 2
    assert json.loads((tmp_path / "qa" / RECORD_FILE).read_text())["failed"] == records[0]["failed"]


def test_a_queue_is_checked_whole_before_any_run_starts(tmp_path, capsys, monkeypatch) -> None:
    from pimbrl.experiments.engine import QueuedStudy, run_studies

    a, b = load_spec(_spec(tmp_path, name="a.yaml")), load_spec(_spec(tmp_path, name="b.yaml"))
    with pytest.raises(ConfigError, match="studies a and b of the queue share a run directory"):
        run_studies([QueuedStudy(a, tmp_path / "x"), QueuedStudy(b, tmp_path / "x")], log=lambda m: None)
    start_study(load_spec(_spec(tmp_path, name="c.yaml")), tmp_path / "held")  # b's directory holds another study
    with pytest.raises(ConfigError, match="holds the study 'c', not 'b'"):
        run_studies([QueuedStudy(a, tmp_path / "qa"), QueuedStudy(b, tmp_path / "held")], log=lambda m: None)
    assert not any(p.name == "config.request.json" for p in (tmp_path / "qa").rglob("*"))  # a trained nothing,
    assert not (tmp_path / "qa" / RECORD_FILE).exists() and not (tmp_path / "qa" / "study.json").exists()  # nor started
    from pimbrl.experiments.runner import lock_comparison

    os.close(lock_comparison(tmp_path / "qa"))  # and its directory is free again
    with pytest.raises(ConfigError, match="share a run directory"):  # one inside the other
        run_studies([QueuedStudy(a, tmp_path / "x"), QueuedStudy(b, tmp_path / "x" / "b")], log=lambda m: None)
    monkeypatch.chdir(tmp_path)
    assert main(["study", "run", "a.yaml", "b.yaml", "--run-dir", "x"]) == 2
    assert "with several specs runs each in its own directory with its own archive: drop --run-dir" in capsys.readouterr().err


@pytest.mark.slow
def test_a_seed_free_controller_runs_two_seeds_and_copies_the_first_into_the_rest(tmp_path, monkeypatch) -> None:
    import dataclasses

    from pimbrl.experiments import replicas

    overrides = {"eval_episodes": 3, "holdout_episodes": 2, "model.gains": [1.0]}
    methods = {"feedback": {"method": "feedback"}, "mpc-identified": {"method": "mpc", "seeds": [0, 1, 2],
               "overrides": {"learn.coefficients": {"g": None}}}}  # fmt: skip
    spec = load_spec(_spec(tmp_path, methods={"feedback": methods["feedback"]}, seeds=4, overrides=overrides))
    root = tmp_path / "run"
    from pimbrl.experiments.progress import progress_lines, study_progress

    before = "\n".join(progress_lines(spec, study_progress(spec, root)))
    assert "2 seeds of seed-free controllers left out" in before  # the estimate charges only the probes
    logs: list[str] = []
    record = run_study(spec, root, jobs=2, status=False, log=logs.append)
    copied = [line for line in logs if line.startswith("copy ")]
    assert len(copied) == 2 and "seeds 0 and 1 agree" in copied[0]  # seeds 2 and 3: copies of seed 0
    by_seed = {r["seed"]: r for r in record["runs"]}
    assert [by_seed[s]["replicate_of"] for s in range(4)] == [None, None, "feedback/seed0", "feedback/seed0"]
    assert len({by_seed[s]["holdout_return"] for s in range(4)}) == 1 and all(r["finished"] for r in record["runs"])
    payload = json.loads((root / "feedback" / "seed3" / "config.json").read_text())
    assert payload["config"]["seed"] == 3 and payload["replicate_of"]["checked_against"] == "feedback/seed1"
    assert not (root / "feedback" / "seed3" / "run.lock").exists() and not list((root / "feedback").glob(".*"))
    assert not record["mismatched"] and not record["missing"]
    again: list[str] = []
    run_study(spec, root, jobs=2, status=False, log=again.append)  # nothing to do the second time
    assert "4 finished, 0 to run" in again[0] and not any(line.startswith("copy ") for line in again)
    # a planted link in the source: refused (nothing followed), no half-made copy left
    runs = {r.seed: r for r in plan_study(spec, root)}
    stranger = dataclasses.replace(runs[3], seed=7, path=root / "feedback" / "seed7")
    (root / "feedback" / "seed0" / "control.json").unlink()
    (root / "feedback" / "seed0" / "control.json").symlink_to(tmp_path / "s.yaml")
    with pytest.raises(ValueError, match="link"):
        replicas.replicate(runs[0], stranger, runs[1], root)
    assert not stranger.path.exists() and not list((root / "feedback").glob(".*"))
    # probes that disagree: nothing is copied, every seed runs
    monkeypatch.setattr(replicas, "same_episodes", lambda a, b: False)
    other = tmp_path / "other"
    logs.clear()
    record = run_study(spec, other, jobs=2, status=False, log=logs.append)
    assert not any(line.startswith("copy ") for line in logs) and all(r["replicate_of"] is None for r in record["runs"])
    import shutil

    for seed in (2, 3):  # probes that finished and disagree: the other seeds will train, and the estimate counts them
        shutil.rmtree(other / "feedback" / f"seed{seed}")
    text = "\n".join(progress_lines(spec, study_progress(spec, other)))
    assert "2 not started" in text and "left out" not in text
    plan = plan_study(load_spec(_spec(tmp_path, name="m.yaml", methods=methods, seeds=3, overrides=overrides)), tmp_path / "m")
    assert [replicas.seed_free(r) for r in plan if r.seed == 0] == [True, False]  # an identifying MPC draws transitions
    grid = load_spec(_spec(tmp_path, name="g.yaml", methods={"feedback": methods["feedback"]}, seeds=3,
                           overrides={"eval_episodes": 3}, grid={"model.gains": [[1.0], [3.0]]}))  # fmt: skip
    runs = plan_study(grid, tmp_path / "g")
    assert len(replicas.plan_replicas(runs, runs)) == 2  # list-valued grid settings group too: one copy per setting
    # a copy that cannot be made (here: any error) is trained instead, and the record is still written
    monkeypatch.setattr(replicas, "same_episodes", lambda a, b: True)
    monkeypatch.setattr(replicas, "replicate", lambda *a: (_ for _ in ()).throw(OSError("disk full")))
    logs.clear()
    record = run_study(spec, tmp_path / "third", jobs=2, status=False, log=logs.append)
    assert sum("no copy for feedback seed" in line and "disk full" in line for line in logs) == 2
    assert len(record["runs"]) == 4 and all(r["finished"] and r["replicate_of"] is None for r in record["runs"])


@pytest.mark.slow
def test_a_model_based_run_logs_its_metrics_at_every_evaluation_so_its_curve_counts_imagined_transitions(tmp_path) -> None:
    from pimbrl.training import run_training
    from pimbrl.training.rundir import RunDirectory

    cfg = resolve_config("pimbrl/Pendulum-v0", {"method": "mbrl", **TINY, "total_steps": 120, "log_every": 50,
                                                "imagine.rollout_length": 2})  # fmt: skip
    run_training(cfg, tmp_path / "run", progress=False)
    steps = [int(line.split(",")[0]) for line in (tmp_path / "run" / "metrics.csv").read_text().splitlines()[1:]]
    assert steps == [40, 50, 80, 100, 120]  # every log_every, every evaluation, once each
    curve = RunDirectory(tmp_path / "run").result()["curve"]
    assert curve["step"] == [40.0, 80.0, 120.0] and None not in curve["imagined_total"]
    assert curve["imagined_total"][-1] > 0


@pytest.mark.slow
def test_the_pages_take_the_hand_written_preamble_from_whichever_spec_folder_has_it(tmp_path, monkeypatch) -> None:
    monkeypatch.chdir(tmp_path)
    paths = []
    for folder in ("confirmatory", "studies"):
        (tmp_path / folder).mkdir()
        path = _spec(tmp_path / folder, name=f"{folder}.yaml", record={"path": f"{folder}.json", "format": "study"})
        spec = load_spec(path)
        record = {"runs": _fake_runs({"mfrl": -900.0}, 2), "thresholds": {}, "spec_sha256": spec.sha256}
        (tmp_path / folder / f"{folder}.json").write_text(json.dumps(record))
        paths.append(str(path))
    (tmp_path / "studies" / "_reproduce.md").write_text("## The paper's figures\n\nby hand\n")
    assert main(["study", "report", "--pages", str(tmp_path / "docs"), *paths]) == 0  # the folder without it first
    assert "## The paper's figures\n\nby hand" in (tmp_path / "docs" / "reproduce.md").read_text()


def test_best_recipe_sections_resolve_to_each_chosen_arm_or_are_refused_with_the_reason(tmp_path, monkeypatch) -> None:
    from pimbrl.experiments.report import _recipe_sections
    from pimbrl.systems.presets import Recipe
    from pimbrl.training import config as config_module
    from pimbrl.training.config import config_to_dict

    methods = {"td3-b64": {"method": "mfrl", "overrides": {"agent.batch_size": 64}},
               "crossq-lr": {"method": "mfrl", "overrides": {"agent": "crossq", "agent.actor_lr": 3e-3}},
               "mbrl-l3": {"method": "mbrl", "overrides": {"imagine.rollout_length": 3, "eval_protocol": "validation"}}}  # fmt: skip
    tuning = {"mfrl": ["td3-b64"], "crossq": ["crossq-lr"], "mbrl": ["mbrl-l3"]}
    spec = load_spec(_spec(tmp_path, methods=methods, tuning=tuning, seeds=1, overrides={"eval_protocol": "validation"}))
    chosen = {f: {"candidates": c, "iqm": {c[0]: -1.0}, "chosen": c[0]} for f, c in tuning.items()}
    sections, why = _recipe_sections(spec, chosen)
    assert why == "" and "eval_protocol" not in sections["methods"]["mbrl"]  # an arm's protocol is not a recipe's
    assert sections["agents"]["crossq"]["agent.batch_size"] != 64  # TD3's tuned batch does not leak into CrossQ's
    default = config_module.recipe_of("pimbrl/Pendulum-v0")
    best = Recipe("best", settings=default.settings, model_based=default.model_based, methods=sections["methods"],
                  agents=sections["agents"])  # fmt: skip
    monkeypatch.setattr(config_module, "recipe_of", lambda env, preset=None: best)
    for run in plan_study(spec, tmp_path / "r"):  # each chosen arm's configuration comes back from the recipe
        agent = "crossq" if run.arm == "crossq-lr" else "td3"
        again = resolve_config("pimbrl/Pendulum-v0", {"method": run.config.method.name, "agent": agent, "seed": run.seed,
                                                      "eval_protocol": "validation"})  # fmt: skip
        assert config_to_dict(again) == config_to_dict(run.config), run.arm
    monkeypatch.undo()
    two = {**methods, "crossq-utd5": {"method": "mfrl", "overrides": {"agent": "crossq", "utd": 5.0}}}
    spec2 = load_spec(_spec(tmp_path, name="t2.yaml", methods=two, seeds=1, overrides={"eval_protocol": "validation"},
                            tuning={**tuning, "crossq-matched": ["crossq-utd5"]}))  # fmt: skip
    chosen2 = {**chosen, "crossq-matched": {"candidates": ["crossq-utd5"], "iqm": {"crossq-utd5": 0.0}, "chosen": "crossq-utd5"}}
    assert _recipe_sections(spec2, chosen2) == ({}, "two families tune the agent crossq")
    grid = load_spec(_spec(tmp_path, name="t3.yaml", methods=methods, seeds=1, tuning=tuning, grid={"agent.gamma": [0.9, 0.99]},
                           overrides={"eval_protocol": "validation"}))  # fmt: skip
    assert _recipe_sections(grid, chosen)[1] == "the study has a grid (its choices are per setting)"
    shared = load_spec(_spec(tmp_path, name="t4.yaml", methods=methods, seeds=1, tuning=tuning,
                             overrides={"eval_protocol": "validation", "total_steps": 300}))  # fmt: skip
    assert 'Every candidate also ran with the study\'s overrides {"total_steps": 300}' in _recipe_sections(shared, chosen)[1]


@pytest.mark.slow
def test_an_error_in_one_study_of_a_queue_drops_its_waiting_runs_and_the_others_train(tmp_path, monkeypatch) -> None:
    import pimbrl.experiments.archive as archive
    from pimbrl.experiments.engine import QueuedStudy, run_studies
    from pimbrl.experiments.runner import lock_comparison

    def broken_archive(spec, *args, **kwargs):
        raise RuntimeError(f"the archive of {spec.name} is broken")

    monkeypatch.setattr(archive, "archive_study", broken_archive)
    a = load_spec(_spec(tmp_path, name="a.yaml", seeds=[0, 1]))
    b = load_spec(_spec(tmp_path, name="b.yaml"))
    queue = [QueuedStudy(a, tmp_path / "qa", archive=tmp_path / "arch-a", keep_archive=True), QueuedStudy(b, tmp_path / "qb")]
    lines: list[str] = []
    with pytest.raises(RuntimeError, match="the archive of a is broken"):  # raised once the queue has ended
        run_studies(queue, jobs=1, status=False, log=lines.append)
    assert any("its waiting runs are dropped, the queue goes on" in line for line in lines)
    assert not any(line.startswith("start ") and "qa/mfrl/seed1" in line for line in lines)  # dropped, never started
    assert not (tmp_path / "qa" / "mfrl" / "seed1" / "config.json").exists() and not (tmp_path / "qa" / RECORD_FILE).exists()
    assert json.loads((tmp_path / "qb" / RECORD_FILE).read_text())["runs"][0]["finished"]
    os.close(lock_comparison(tmp_path / "qa"))  # its directory is free again
