"""Provenance in every run record: the CPU model, the commit, and what the method used to get its result."""

from __future__ import annotations

import json
import re
import subprocess
from pathlib import Path

import pytest

from pimbrl.config import ConfigError
from pimbrl.training import create_run, resolve_config, train
from pimbrl.training.rundir import cpu_identity, cpu_model, source_commit

from .settings import ENV_IDS, for_method

ROOT = Path(__file__).resolve().parent.parent
SHORT = {"total_steps": 300, "warmup_steps": 50, "update_after": 100, "eval_every": 300, "eval_episodes": 2,
         "agent.hidden": (16, 16), "agent.batch_size": 16, "model.start_after": 100, "fit.steps": 1,
         "fit.batch_size": 16, "imagine.rollouts": 4, "imagine.rollout_length": 3, "check.threshold": 1e3,
         "check.validation_size": 32}  # fmt: skip


def test_the_cpu_is_named_by_its_model_and_the_code_by_its_commit() -> None:
    cpu = cpu_model()
    assert cpu and cpu not in ("x86_64", "aarch64", "unknown")
    cpuinfo = Path("/proc/cpuinfo")
    if cpuinfo.exists() and "model name" in cpuinfo.read_text():
        assert cpu in cpuinfo.read_text()
    identity = cpu_identity()
    if cpuinfo.exists() and "cpu family" in cpuinfo.read_text():  # a masked model name is told apart by these
        family = re.search(r"^cpu family\s*:\s*(\d+)", cpuinfo.read_text(), re.M)
        assert identity is not None and family is not None and f" family {family.group(1)} model " in identity
        assert re.fullmatch(r"\S+ family \d+ model \d+ stepping \d+, flags [0-9a-f]{8}", identity)
    head = subprocess.run(["git", "rev-parse", "HEAD"], cwd=ROOT, capture_output=True, text=True)
    if head.returncode == 0:  # a checkout: the commit is read from .git without running git
        assert source_commit() == head.stdout.strip()


def _run(tmp_path, name: str, method: str, **extra) -> tuple[dict, dict]:
    cfg = resolve_config(ENV_IDS["pendulum"], {"method": method, **for_method(SHORT, method), **extra})
    run = create_run(cfg, tmp_path / name, progress=False)
    summary = train(run)
    payload = json.loads((tmp_path / name / "config.json").read_text())
    return payload, summary.__dict__


@pytest.mark.slow
def test_a_run_records_where_it_ran_and_what_its_method_used(tmp_path) -> None:
    payload, mf = _run(tmp_path, "mf", "mfrl")
    assert payload["provenance"]["cpu"] == cpu_model() and payload["provenance"]["cores"] >= 1
    assert payload["provenance"]["cpu_id"] == cpu_identity()
    assert payload["provenance"]["commit"] == source_commit()
    assert mf["real_transitions"] == 300 and mf["imagined_transitions"] == mf["scheme_transitions"] == 0
    _, mb = _run(tmp_path, "mb", "mbrl")
    assert mb["imagined_transitions"] > 0 and mb["scheme_transitions"] == 0  # a network's imagination
    _, known = _run(tmp_path, "known", "known-scheme", **{"finetune.at_return": 1e9, "finetune.episodes": 2})
    assert known["scheme_transitions"] >= known["imagined_transitions"] > 0  # the known equation's transitions
    assert known["validation_transitions"] == 2 * 200  # the switch's two validation episodes at the one evaluation
    recorded = json.loads((tmp_path / "known" / "config.json").read_text())["summary"]
    assert recorded["scheme_transitions"] == known["scheme_transitions"]


@pytest.mark.slow
def test_policy_selection_s_steps_in_the_scheme_are_counted_and_old_checkpoints_say_unknown(tmp_path) -> None:
    _, plain = _run(tmp_path, "plain", "known-scheme")
    _, selecting = _run(tmp_path, "select", "known-scheme", **{"imagine.select_episodes": 2})
    assert plain["scheme_transitions"] == plain["imagined_transitions"]  # imagination only (no step blew up)
    assert selecting["scheme_transitions"] >= selecting["imagined_transitions"] + 2 * 200  # two whole episodes
    from pimbrl.training import load_run

    run = load_run(tmp_path / "select")
    state = run.model.state_dict()
    for key in ("validation_transitions", "model_transitions"):
        state.pop(key)  # as a checkpoint written before they were counted
    run.model.load_state_dict(state)
    summary = run.summary()
    assert summary.scheme_transitions is None and summary.validation_transitions is None
    run.run_dir.close()


def test_the_commit_is_read_from_a_worktree_and_not_from_a_project_around_an_install(tmp_path, monkeypatch) -> None:
    import pimbrl.training.rundir as rundir

    repo = tmp_path / "repo"
    (repo / "src" / "pimbrl" / "training").mkdir(parents=True)
    (repo / "pyproject.toml").write_text("")
    gitdir = tmp_path / "main.git" / "worktrees" / "repo"
    (gitdir).mkdir(parents=True)
    (repo / ".git").write_text(f"gitdir: {gitdir}\n")
    (gitdir / "HEAD").write_text("ref: refs/heads/topic\n")
    (gitdir / "commondir").write_text("../..\n")
    (tmp_path / "main.git" / "refs" / "heads").mkdir(parents=True)
    (tmp_path / "main.git" / "refs" / "heads" / "topic").write_text("abc123\n")
    monkeypatch.setattr(rundir, "__file__", str(repo / "src" / "pimbrl" / "training" / "rundir.py"))
    assert rundir.source_commit() == "abc123"
    site = tmp_path / "project" / ".venv" / "lib" / "site-packages" / "pimbrl" / "training"
    site.mkdir(parents=True)
    (tmp_path / "project" / ".git").mkdir()
    monkeypatch.setattr(rundir, "__file__", str(site / "rundir.py"))
    assert rundir.source_commit() is None  # an installed pimbrl is not the surrounding project's commit


def test_a_system_declared_again_is_checked_with_its_new_coefficients() -> None:
    from pimbrl.systems import Coefficient, declare

    from .test_systems import VanDerPol

    class Narrow(VanDerPol):
        coefficients = {"mu": Coefficient(1.0, low=0.0, high=2.0)}  # noqa: RUF012 - the API's form

    class Wide(VanDerPol):
        coefficients = {"mu": Coefficient(1.0, low=0.0, high=8.0)}  # noqa: RUF012 - the API's form

    declare(Narrow, "test/ReDeclared-v0")
    with pytest.raises(ConfigError, match="mu"):
        resolve_config("test/ReDeclared-v0", {"env_kwargs": {"mu": 6.0}})
    declare(Wide, "test/ReDeclared-v0")  # the same id, declared again: its new bounds apply
    assert resolve_config("test/ReDeclared-v0", {"env_kwargs": {"mu": 6.0}}).env_kwargs == {"mu": 6.0}
