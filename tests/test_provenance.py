"""Provenance in every run record: the CPU model, the commit, and what the method used to get its result."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

from pimbrl.training import create_run, resolve_config, train
from pimbrl.training.rundir import cpu_model, source_commit

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
    head = subprocess.run(["git", "rev-parse", "HEAD"], cwd=ROOT, capture_output=True, text=True)
    if head.returncode == 0:  # a checkout: the commit is read from .git without running git
        assert source_commit() == head.stdout.strip()


def _run(tmp_path, name: str, method: str, **extra) -> tuple[dict, dict]:
    cfg = resolve_config(ENV_IDS["pendulum"], {"method": method, **for_method(SHORT, method), **extra})
    run = create_run(cfg, tmp_path / name, progress=False)
    summary = train(run)
    payload = json.loads((tmp_path / name / "config.json").read_text())
    return payload, summary.__dict__


def test_a_run_records_where_it_ran_and_what_its_method_used(tmp_path) -> None:
    payload, mf = _run(tmp_path, "mf", "mfrl")
    assert payload["provenance"]["cpu"] == cpu_model() and payload["provenance"]["cores"] >= 1
    assert payload["provenance"]["commit"] == source_commit()
    assert mf["real_transitions"] == 300 and mf["imagined_transitions"] == mf["scheme_transitions"] == 0
    _, mb = _run(tmp_path, "mb", "mbrl")
    assert mb["imagined_transitions"] > 0 and mb["scheme_transitions"] == 0  # a network's imagination
    _, known = _run(tmp_path, "known", "known-scheme", **{"finetune.at_return": 1e9, "finetune.episodes": 2})
    assert known["scheme_transitions"] == known["imagined_transitions"] > 0  # the known equation's transitions
    assert known["validation_transitions"] == 2 * 200  # the switch's two validation episodes at the one evaluation
    recorded = json.loads((tmp_path / "known" / "config.json").read_text())["summary"]
    assert recorded["scheme_transitions"] == known["scheme_transitions"]
