"""The Dyna loop (MBRL, PiMBRL): every method on every environment, phase order, resume mid-phase, compare."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from pimbrl.cli import main
from pimbrl.training import Run, RunDirectory, create_run, resolve_config, train
from pimbrl.training.config import has_setting

from .conftest import SMALL_POOL
from .settings import DYNA_SMOKE_SETTINGS, ENV_IDS, SMALL_MODEL_SETTINGS, TINY_SETTINGS, flags, for_method
from .test_training import TINY, _table, kill_when

SMALL_MODEL = flags(SMALL_MODEL_SETTINGS)
#: the model-based smoke runs' `pimbrl train` flags (for the command-line tests)
DYNA_SMOKE = {env: flags(settings) for env, settings in DYNA_SMOKE_SETTINGS.items()}


#: a short Pendulum run with small networks and its model from step 100
SHORT_PENDULUM = {"total_steps": 300, "warmup_steps": 50, "update_after": 100, "eval_every": 300, "eval_episodes": 2,
                  "agent.hidden": (16, 16), "agent.batch_size": 16, "model.start_after": 100}  # fmt: skip


def _for_method(args: list[str], method: str) -> list[str]:
    """Flags ``args`` without the settings ``method`` does not have (mbrl: no physics loss; given, an error)."""
    out: list[str] = []
    i = 0
    while i < len(args):
        flag = args[i]
        takes_value = flag.startswith("--") and flag != "--quiet"
        if takes_value and "." in flag and not has_setting(method, "td3", flag[2:].replace("-", "_")):
            i += 2
            continue
        out += args[i : i + 2] if takes_value else [flag]
        i += 2 if takes_value else 1
    return out


@pytest.mark.parametrize("method", ["mbrl", "pimbrl"])
@pytest.mark.parametrize("env", list(DYNA_SMOKE))
@pytest.mark.slow
def test_model_based_methods_run_on_every_env(env: str, method: str, tmp_path) -> None:
    run = tmp_path / "run"
    smoke = _for_method(DYNA_SMOKE[env], method)
    assert main(["train", env, "--method", method, "--run-dir", str(run), *smoke, *TINY, *SMALL_MODEL]) == 0
    payload = json.loads((run / "config.json").read_text())
    assert payload["status"] == "finished" and payload["config"]["method"]["name"] == method
    metrics = RunDirectory(run).metrics([]).read()
    last = metrics[-1]
    assert float(last["model/data_loss"]) >= 0 and last["model/in_use"] == "1"
    assert int(last["imagined_total"]) > 0 and float(last["update_to_data"]) > 0
    assert ("model/physics_loss" in last) == (method == "pimbrl")
    if method == "pimbrl":
        assert float(last["model/physics_loss"]) >= 0
    assert all(float(last[f"time/{p}_s"]) >= 0 for p in ("model_train", "imagine", "agent_update", "evaluate"))


class Recorder:
    """Records, after every model phase, what ran (through the loop's event hook)."""

    def __init__(self) -> None:
        self.log: list[dict] = []
        self.events: list[tuple[str, int]] = []
        self._steps = 0
        self._imagined = 0
        self._imagined_len = 0

    def __call__(self, name: str, run: Run) -> None:
        self.events.append((name, run.t))
        model = run.model
        if name == "act" and model is not None:  # the state the next model phase starts from
            self._steps = model.trainer.steps
            self._imagined = model.imagined_total
            self._imagined_len = len(model.imagined)
        if name == "model_phase":
            trained = model.trainer.steps > self._steps
            self.log.append(
                {
                    "t": run.t,
                    "real": len(run.real),
                    "imagined": self._imagined_len,  # what the phase saw when it decided on the physics loss
                    "model_trained": trained,
                    "physics": "model/physics_loss" in model.metrics and trained,
                    "imagined_now": model.imagined_total > self._imagined,
                    "in_use": model.in_use,
                    "agent_updates": run.agent.n_updates,
                }
            )


def _record(cfg, path) -> tuple[Recorder, Run]:
    recorder = Recorder()
    run = create_run(cfg, str(path), progress=False)
    train(run, on_event=recorder)
    return recorder, run


@pytest.mark.slow
def test_phases_start_in_the_configured_order(tmp_path) -> None:
    cfg = resolve_config(
        "pimbrl/Pendulum-v0",
        {
            "method": "pimbrl",
            "total_steps": 600,
            "warmup_steps": 50,
            "update_after": 100,
            "update_every": 50,
            "eval_every": 600,
            "eval_episodes": 2,
            "agent.hidden": (16, 16),
            "agent.batch_size": 16,
            "model.start_after": 200,
            "physics.start_after": 400,
            "fit.steps": 2,
            "fit.batch_size": 16,
            "imagine.rollouts": 8,
            "imagine.rollout_length": 5,
            "check.threshold": 1e3,
            "check.validation_size": 32,
        },
    )
    recorder, _ = _record(cfg, tmp_path / "run")
    log = recorder.log
    assert log[0]["t"] == 100  # update_after
    for entry in log:
        assert entry["model_trained"] == (entry["real"] >= 200)  # n_sM
        assert entry["physics"] == (entry["model_trained"] and entry["real"] + entry["imagined"] >= 400 and entry["imagined"] > 0)
        assert entry["imagined_now"] == entry["in_use"]  # imagination only with a usable model
        assert not entry["in_use"] or entry["model_trained"]
    assert any(e["physics"] for e in log) and not log[0]["physics"]
    # a model that never meets lambda is never used: MBRL then equals MFRL in what the agent sees
    strict = resolve_config(
        "pimbrl/Pendulum-v0",
        {
            "method": "mbrl",
            **SHORT_PENDULUM,
            "fit.steps": 1,
            "fit.batch_size": 16,
            "check.threshold": 1e-12,
            "check.validation_size": 32,
        },
    )
    r2, run2 = _record(strict, tmp_path / "strict")
    assert not any(e["in_use"] for e in r2.log) and run2.model.imagined_total == 0


@pytest.mark.slow  # a few seconds: the whole suite runs it, the fast tier does not
def test_finetune_switch_stops_the_model(tmp_path) -> None:
    cfg = resolve_config(
        "pimbrl/Pendulum-v0",
        {
            "method": "pimbrl",
            "total_steps": 400,
            "warmup_steps": 50,
            "update_after": 100,
            "eval_every": 400,
            "eval_episodes": 2,
            "agent.hidden": (16, 16),
            "agent.batch_size": 16,
            "model.start_after": 100,
            "physics.start_after": 100,
            "fit.steps": 1,
            "fit.batch_size": 16,
            "imagine.rollouts": 4,
            "check.threshold": 1e3,
            "check.validation_size": 32,
            "finetune.after": 250,
        },
    )
    recorder, _ = _record(cfg, tmp_path / "run")
    assert all(e["in_use"] for e in recorder.log if e["t"] < 250)
    assert not any(e["in_use"] or e["model_trained"] for e in recorder.log if e["t"] >= 250)


RESUME_DYNA = [
    "cartpole", "--method", "pimbrl", "--steps", "800", "--warmup-steps", "100", "--update-after", "100",
    "--eval-every", "200", "--eval-episodes", "4", "--checkpoint-every", "100", "--log-every", "100",
    "--model.start-after", "100", "--physics.start-after", "150", "--fit.steps", "5",
    "--check.threshold", "1e3", "--imagine.rollout-length", "30", "--imagine.select-episodes", "3", *TINY, *SMALL_MODEL,
]  # fmt: skip


@pytest.mark.slow
def test_kill_and_resume_in_the_middle_of_the_model_based_phase(tmp_path) -> None:
    ref, killed = tmp_path / "ref", tmp_path / "killed"
    assert main(["train", *RESUME_DYNA, "--run-dir", str(ref)]) == 0

    def ready(run) -> bool:  # the model is trained, in use and imagining, and a checkpoint exists
        rows = RunDirectory(run).metrics([]).read() if (run / "metrics.csv").exists() else []
        return (run / "checkpoints" / "latest.pt").exists() and len(rows) >= 4 and int(rows[-1]["imagined_total"]) > 0

    kill_when(RESUME_DYNA, killed, ready)
    assert main(["resume", str(killed), "--quiet"]) == 0
    drop = ("wall_s", "steps_per_s")
    for name in ("evaluations.csv", "episodes.csv", "metrics.csv", "selection.csv"):
        assert _table(ref, name, drop) == _table(killed, name, drop), name
    assert len(_table(ref, "selection.csv", drop)) == 4  # one row per evaluation, kept through the kill


@pytest.mark.slow
def test_compare_runs_methods_and_skips_finished_runs(tmp_path, capsys) -> None:
    root = tmp_path / "cmp"
    args = [
        "compare",
        "cartpole",
        "--methods",
        "mfrl,pimbrl,mfrl-matched",
        "--seeds",
        "0,1",
        "--run-dir",
        str(root),
        "--steps",
        "150",
    ]
    extra = ["--", "--warmup-steps", "50", "--update-after", "50", "--eval-every", "100", "--eval-episodes", "3",
             "--model.start-after", "50", "--physics.start-after", "80", "--fit.steps", "2",
             "--imagine.rollout-length", "10", *TINY, *SMALL_MODEL]  # fmt: skip
    assert main([*args[:-2], "--jobs", "2", *args[-2:], *extra]) == 0
    out = capsys.readouterr().out
    assert "steps ratio pimbrl/mfrl" in out
    summary = json.loads((root / "summary.json").read_text())
    assert {r["method"] for r in summary["runs"]} == {"mfrl", "pimbrl", "mfrl-matched"} and len(summary["runs"]) == 6
    matched = resolve_config("pimbrl/CartPole-v0", {"method": "pimbrl"}).utd
    assert json.loads((root / "mfrl-matched" / "seed0" / "config.json").read_text())["config"]["utd"] == matched
    assert (root / "curves.png").stat().st_size > 10_000 and (root / "summary.csv").exists()
    mtime = (root / "pimbrl" / "seed1" / "evaluations.csv").stat().st_mtime
    assert main(args + extra) == 0  # nothing to redo
    assert (root / "pimbrl" / "seed1" / "evaluations.csv").stat().st_mtime == mtime
    # --no-run summarises what exists and starts nothing: seed 2 is planned but not trained
    assert main([*args[:5], "0,1,2", *args[6:], "--no-run"]) == 0
    assert not (root / "mfrl" / "seed2").exists()
    assert len(json.loads((root / "summary.json").read_text())["runs"]) == 6
    # --no-run on a directory without runs is an error that says where it looked, and creates nothing
    empty = tmp_path / "nothing-here"
    assert main(["compare", "cartpole", "--methods", "mfrl", "--seeds", "1", "--run-dir", str(empty), "--no-run"]) == 2
    assert "no run under" in capsys.readouterr().err and not empty.exists()


def test_pimbrl_needs_an_equation(tmp_path, capsys) -> None:
    assert main(["train", "Pendulum-v1", "--method", "pimbrl", "--run-dir", str(tmp_path / "r"), "--quiet"]) == 2
    assert "pimbrl needs the system's equation, and Pendulum-v1 declares none" in capsys.readouterr().err


def test_small_pool_is_used(ks_small_pools) -> None:
    assert len(ks_small_pools[0].states) == SMALL_POOL.n_train


def test_step_ratio_counts_unfinished_runs_at_their_budget() -> None:
    from pimbrl.experiments.compare import ratio_lines, step_ratio, steps_text, summarize_method

    def run(steps_to: int | None, steps: int) -> dict:
        return {"steps_to_threshold": steps_to, "steps": steps, "final_return": 0.0, "wall_s": 1.0, "update_to_data": 1.0}

    pim = summarize_method([run(1000, 5000), run(2000, 5000)])
    assert pim["steps_to_threshold_mean"] == 1500.0
    mfrl = summarize_method([run(3000, 15000), run(None, 15000), run(None, 12000)])
    assert mfrl["steps_to_threshold_mean"] is None and mfrl["reached"] == 1
    assert mfrl["steps_to_threshold_lower_bound"] == 10000.0  # (3000 + 15000 + 12000) / 3
    ratio = step_ratio(pim, mfrl)
    assert ratio["value"] == pytest.approx(0.15) and ratio["note"].startswith("upper bound: 2 of 3")
    assert step_ratio(pim, pim)["value"] == 1.0 and step_ratio(mfrl, pim)["value"] is None
    # medians: pim's is measured (1500); mfrl's middle run did not reach it, so its median exceeds 12,000
    assert pim["steps_to_threshold_median"] == 1500.0 and mfrl["steps_to_threshold_median"] is None
    assert mfrl["steps_to_threshold_median_above"] == 12000 and mfrl["steps_to_threshold_median_at_most"] is None
    assert ratio["median"]["value"] == pytest.approx(0.125) and ratio["median"]["note"].startswith("upper bound")
    assert step_ratio(pim, pim)["median"]["value"] == 1.0
    assert step_ratio(mfrl, pim)["median"]["value"] is None
    # steps as measured or bounded, for a run or a censored median (steps_ratio.py, run_partial_physics.py)
    assert steps_text(1500.0, None) == "1,500" and steps_text(None, 12000) == "> 12,000"
    assert steps_text(None, 50000, 60000) == "> 50,000 and <= 60,000" and steps_text(None, None) == "unknown"
    # the lines `pimbrl compare` prints and collect_results.py writes: each ratio, then its ratio of the medians
    lines = ratio_lines({"pimbrl/mfrl": ratio, "mfrl/pimbrl": step_ratio(mfrl, pim)}, missing="—")
    assert lines[0] == f"pimbrl/mfrl: 0.150 ({ratio['note']})"
    assert lines[1] == f"pimbrl/mfrl, medians: 0.125 ({ratio['median']['note']})"
    assert lines[2].startswith("mfrl/pimbrl: — (") and lines[3].startswith("mfrl/pimbrl, medians: — (")


def test_the_median_steps_to_threshold_is_measured_when_the_middle_runs_reached_it() -> None:
    from pimbrl.experiments.compare import median_steps_to_threshold, step_ratio, summarize_method

    def runs(*pairs: tuple[int | None, int]) -> list[dict]:
        return [
            {"steps_to_threshold": s, "steps": b, "final_return": 0.0, "wall_s": 1.0, "update_to_data": 1.0} for s, b in pairs
        ]

    def median(*pairs: tuple[int | None, int]) -> tuple:
        m = median_steps_to_threshold(runs(*pairs))
        return m["steps_to_threshold_median"], m["steps_to_threshold_median_above"], m["steps_to_threshold_median_at_most"]

    # four of six reached: the middle two (55,000 and 57,500) are measured, the two censored runs sort last
    six = runs((37500, 60000), (55000, 60000), (None, 60000), (57500, 60000), (32500, 60000), (None, 60000))
    assert median_steps_to_threshold(six)["steps_to_threshold_median"] == 56250.0
    # three of six: the median averages 57,500 and a run beyond 60,000, so it is above 58,750, unbounded above
    assert median((37500, 60000), (None, 60000), (None, 60000), (57500, 60000), (32500, 60000), (None, 60000)) == (
        None,
        58750.0,
        None,
    )
    # a censored run with a short budget may sort anywhere above it: here the median lies in (4,000, 5,000]
    assert median((5000, 6000), (None, 4000), (3000, 6000)) == (None, 4000.0, 5000.0)
    # ... or it may not matter: the median is 3,000 whatever the censored run needed beyond 4,000
    assert median((1000, 6000), (2000, 6000), (3000, 6000), (50000, 60000), (None, 4000)) == (3000.0, None, None)
    assert median() == (None, None, None)
    # a's median bounded above (5,000) over b's measured one: an upper bound on the ratio
    short = summarize_method(runs((5000, 6000), (None, 4000), (3000, 6000)))
    ratio = step_ratio(short, summarize_method(six))["median"]
    assert ratio["value"] == pytest.approx(5000 / 56250) and ratio["note"].startswith("upper bound")
    assert step_ratio(summarize_method(six), short)["median"]["value"] == pytest.approx(56250 / 4000)


@pytest.mark.parametrize("fraction", [0.0, 1.0])
@pytest.mark.slow
def test_reset_starts_imagine_episodes_from_the_training_pool(tmp_path, ks_small_pools, fraction: float) -> None:
    """``imagine.reset_start_fraction`` 1: every imagined rollout starts at step 0 from a training-pool state
    (never a test-pool one); 0: from the real buffer's states, which lie later in their episodes."""
    settings = {**DYNA_SMOKE_SETTINGS["ks"], **TINY_SETTINGS, **SMALL_MODEL_SETTINGS, "imagine.reset_start_fraction": fraction}
    cfg = resolve_config(ENV_IDS["ks"], {"method": "known-scheme", **for_method(settings, "known-scheme")})
    run = create_run(cfg, tmp_path / "run", progress=False)
    train(run)
    model = run.model
    assert model is not None and model.imagined_total > 0
    n = len(model.imagined)
    idx = torch.arange(n)
    k = model.imagined.extra("k", idx).reshape(-1).long()
    states = model.imagined.extra("state", idx).double().numpy()
    train_pool, test_pool = (pool.states for pool in ks_small_pools)
    first = states[(k == 0).numpy()]

    def rows_of(pool: np.ndarray, xs: np.ndarray) -> np.ndarray:
        return np.array([np.abs(pool - x).max(axis=1).min() < 1e-5 for x in xs], dtype=bool)

    if fraction == 1.0:
        assert int(k.max()) < 3  # the rollout length of DYNA_SMOKE: nothing but fresh episodes
        assert len(first) == n // 3 and len(first) % 16 == 0  # one start per rollout (16 per phase)
        assert rows_of(train_pool, first).all() and not rows_of(test_pool, first).any()
    else:
        assert int(k.max()) >= 20  # starts at the real buffer's steps (collected from step 0 on, warm-up 20)


@pytest.mark.slow
def test_start_shares_that_round_up_together_still_fit_the_rollouts(tmp_path) -> None:
    """3 rollouts, half continued and half from resets: each share rounds to 2, yet 3 rollouts start."""
    cfg = resolve_config(
        "pimbrl/Pendulum-v0",
        {
            "method": "known-scheme",
            **SHORT_PENDULUM,
            "imagine.rollouts": 3,
            "imagine.rollout_length": 2,
            "check.threshold": 1e3,
            "check.validation_size": 32,
            "imagine.imagined_start_fraction": 0.5,
            "imagine.reset_start_fraction": 0.5,
        },
    )
    run = create_run(cfg, tmp_path / "run", progress=False)
    train(run)
    assert run.model is not None
    k = run.model.imagined.extra("k", torch.arange(len(run.model.imagined))).reshape(-1)
    assert run.model.imagined_total == len(k) > 0 and int((k == 0).sum()) > 0  # some episodes began at reset


@pytest.mark.slow
def test_symmetric_reset_starts_are_images_of_training_states(tmp_path, ks_small_pools) -> None:
    """``experimental.reset_start_symmetry``: each fresh imagined episode starts from a training-pool state shifted
    and possibly reflected (``u(x) -> -u(-x)``), mostly not a pool state itself, never a test-pool state."""
    settings = {**DYNA_SMOKE_SETTINGS["ks"], **TINY_SETTINGS, **SMALL_MODEL_SETTINGS, "imagine.reset_start_fraction": 1.0}
    cfg = resolve_config(
        ENV_IDS["ks"],
        {"method": "known-scheme", **for_method(settings, "known-scheme"), "experimental.reset_start_symmetry": True},
    )
    run = create_run(cfg, tmp_path / "run", progress=False)
    train(run)
    model = run.model
    assert model is not None
    idx = torch.arange(len(model.imagined))
    k = model.imagined.extra("k", idx).reshape(-1).long()
    first = model.imagined.extra("state", idx).double().numpy()[(k == 0).numpy()]
    train_pool, test_pool = (pool.states for pool in ks_small_pools)
    n = train_pool.shape[1]
    images = [np.roll(train_pool, s, axis=1) for s in range(n)]
    images += [np.roll(-np.roll(train_pool[:, ::-1], 1, axis=1), s, axis=1) for s in range(n)]
    every = np.concatenate(images)  # all shifts and reflected shifts of the pool

    def nearest(pool: np.ndarray, x: np.ndarray) -> float:
        return float(np.abs(pool - x).max(axis=1).min())

    assert len(first) >= 16
    assert all(nearest(every, x) < 1e-5 for x in first)  # float32 copies of exact images
    assert sum(nearest(train_pool, x) < 1e-5 for x in first) < len(first) // 2  # mostly new states
    assert not any(nearest(test_pool, x) < 1e-5 for x in first)
