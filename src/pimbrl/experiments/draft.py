"""A confirmatory spec drafted from a finished tuning study, by the rules of docs/confirmatory.md.

``pimbrl study draft benchmarks/pending/tune-X.yaml --out benchmarks/confirmatory/confirmatory-X.yaml`` reads
the tuning study's record and writes a spec that is ready to review and register (commit it alone, before
its first run):

* the arms: each method's choice (the highest validation IQM), entry for entry as the tuning report writes
  them, with every candidate's IQM in a comment, and the tuning study's own overrides (a wrong prior, the
  budget) besides ``eval_protocol``;
* fresh seeds (100 and up), ``holdout_episodes`` and ``outcome: holdout``; the tuning study's thresholds;
  with fewer seeds for the other arms (KS), the full number for every arm a hypothesis names and for the
  paper's model-free baseline (TD3 at the recipe's update ratio);
* the hypotheses the protocol states for the families the tuning study has: H1a/H1b (PiMBRL against
  MBRL), H3 (known-scheme Dyna against the tuned model-free arm), H4a/H4b (MPC, DPC against the best RL arm
  by rule) with H4a-ARM/H4b-ARM against every other RL arm (the amendment after confirmatory-burgers), and
  under a wrong prior (``model.prior`` among the overrides) H2a/H2b (the identified scheme against MBRL and
  against the wrong scheme held fixed) in place of H3 and H4;
* the compute plan from the tuning runs' wall-clocks (a seed-free controller trains two seeds).

A tuning study may be amended by later ones of the same system and budget (``pimbrl study draft TUNING
AMENDMENT...``): each amendment's methods replace the first study's of the same name (controlgym Burgers's
scheme methods, tuned again at a stable resolution), and the rules' arms are chosen over the merged choices.

Nothing is chosen here that the protocol does not choose: a setting the draft cannot derive is an error,
and the reviewer edits the text before it is committed, never after.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ..config import ConfigError, load_yaml
from ..training.methods import CONTROL_METHODS
from .report import json_line, rule_choices, study_report
from .spec import StudySpec, parse_spec
from .stats import MIN_RUNS_FOR_VERDICT

__all__ = ["FIRST_SEED", "THRESHOLD_RULE", "draft_confirmatory", "rule_threshold"]

#: the first seed of a confirmatory run (no tuning run used 100 or above)
FIRST_SEED = 100


@dataclass(frozen=True)
class _Family:
    """One tuned method family: its chosen arm, that arm's method and validation IQM, all candidates' IQMs.

    ``source``: the tuning study that chose it; ``summary``: the chosen arm's statistics there (its wall-clock
    and inference cost make the plan).
    """

    name: str
    arm: Any
    iqm: float
    candidates: dict[str, float]
    source: str = ""
    summary: dict[str, Any] = field(default_factory=dict)

    @property
    def method(self) -> str:
        return str(self.arm.method)


def draft_confirmatory(
    spec: StudySpec,
    record: dict[str, Any],
    out: Path | None,
    *,
    seeds: int = 10,
    other_seeds: int | None = None,
    holdout_episodes: int = 100,
    total_steps: int | None = None,
    threshold: float | str | None = None,
    amendments: Sequence[tuple[StudySpec, dict[str, Any]]] = (),
) -> str:
    """The YAML text of the confirmatory spec drafted from tuning study ``spec`` and its ``record``.

    Args:
        spec: the tuning study (``tuning:``), every candidate finished.
        record: its record (:func:`~pimbrl.experiments.report.load_record`).
        out: where the spec will be written (its ``imports`` and ``record`` paths are relative to its folder);
            ``None``: printed, its paths relative to the tuning spec's folder.
        seeds: seeds of every arm (from :data:`FIRST_SEED`), or of the main arms where ``other_seeds`` is
            given: every arm of H1-H3 (H2 under a wrong prior), the best RL arm, MPC, DPC and the best
            controller. An H4 pair with an arm of fewer seeds than a verdict needs is a comparison only.
        other_seeds: seeds of the other arms (KS: 5 and 3), or ``None`` for ``seeds`` everywhere.
        holdout_episodes: the holdout states each run's final policy plays once (its outcome).
        total_steps: the runs' real steps where they differ from the tuning runs' (KS tunes shorter runs).
        threshold: the return of the steps-to-threshold hypotheses (H1a, H3), where the system's recipe
            sets none (chosen on earlier or validation curves, never on the holdout pool); ``"rule"``: the
            one :func:`rule_threshold` derives from the tuning record (docs/confirmatory.md's rule).
        amendments: later tuning studies of the same system, budget and overrides, with their records: each
            one's methods replace ``spec``'s of the same name (its budget of settings x seeds must be the same).
    """
    if seeds < 1 or (other_seeds is not None and not 1 <= other_seeds <= seeds) or holdout_episodes < 1:
        raise ConfigError(
            f"draft: seeds {seeds}, other seeds {other_seeds}, holdout episodes {holdout_episodes}: each must be "
            "at least 1, and the other arms' seeds at most the main arms'"
        )
    families = _families(spec, record)
    tuned = _tuning_run_config(spec)  # the budget and threshold the tuning runs had
    for amending, amending_record in amendments:
        replaced = {f.name: f for f in _families(amending, amending_record)}  # a tuning study of one system
        _check_amendment(spec, tuned, amending)
        families = [replaced.pop(f.name, f) for f in families] + list(replaced.values())
    rules = rule_choices({f.name: f.method for f in families}, {f.name: f.iqm for f in families})
    sources = " and ".join([spec.name, *(a.name for a, _ in amendments)])
    system = spec.systems[0]
    thresholds = [float(t) for t in (record.get("thresholds") or {}).get(system) or spec.thresholds]
    partial = "model.prior" in spec.overrides
    arms = _protocol_arms(spec.name, families, rules, partial)
    by_rule = threshold == "rule"
    if by_rule:
        if tuned.threshold is not None:
            raise ConfigError(
                f"{spec.name}: the system's recipe sets the threshold {tuned.threshold:g}; the rule is for systems "
                "without one: drop --threshold rule"
            )
        threshold = rule_threshold(spec.name, families, arms)
    elif isinstance(threshold, str):
        raise ConfigError(f"draft: threshold must be a number or 'rule', got {threshold!r}")
    if threshold is None and tuned.threshold is not None:
        threshold = float(tuned.threshold)
    if threshold is not None and threshold not in thresholds:
        thresholds.append(threshold)
    roles = ("pimbrl", "mbrl", "known-scheme", "identified-scheme", "mpc", "dpc", "best controller",
             "tuned model-free arm", "best RL arm", "model-free baseline")  # fmt: skip
    main = {str(arms[r]) for r in roles if arms[r]}
    few = other_seeds is not None and other_seeds < MIN_RUNS_FOR_VERDICT
    hypotheses = _hypotheses(spec.name, families, arms, threshold, set() if not few else main)
    if not hypotheses:
        raise ConfigError(f"{spec.name}: its methods give none of the protocol's hypotheses (docs/confirmatory.md)")
    seed_list = list(range(FIRST_SEED, FIRST_SEED + seeds))
    other_list = None if other_seeds is None else list(range(FIRST_SEED, FIRST_SEED + other_seeds))
    overrides = {k: v for k, v in spec.overrides.items() if k != "eval_protocol"}
    tuned_steps = int(tuned.total_steps)
    if total_steps is not None:
        overrides["total_steps"] = total_steps
    overrides["holdout_episodes"] = holdout_episodes
    name = spec.name.replace("tune-", "confirmatory-", 1) if spec.name.startswith("tune-") else f"confirmatory-{spec.name}"
    folder = out.resolve().parent if out is not None else (spec.path.parent if spec.path else Path.cwd())
    where = str(out) if out is not None else f"the draft of {spec.name}"

    lines = [
        "# Pre-registered (docs/confirmatory.md): committed before its first run, never edited after it.",
        f"# Drafted by `pimbrl study draft` from {sources}'s record{'s' if amendments else ''}; reviewed before it was "
        "committed.",
        f"name: {name}",
        "kind: confirmatory",
        "question: >-",
        *_wrapped(_question(spec, system, families, hypotheses, holdout_episodes, sources), "  "),
        f"systems: [{spec.systems[0]}]",
        f"preset: {spec.preset or 'default'}",
        f"seeds: {json_line(seed_list)}",
    ]
    if spec.imports:
        lines.append(f"imports: {json_line([_relative(i, folder) for i in spec.imports])}")
    lines += ["methods:", f"  # {sources}'s choices: the highest IQM of the {spec.outcome} validation return over its seeds"]
    for fam in families:
        others = ", ".join(f"{a} {v:.4g}" for a, v in fam.candidates.items() if a != fam.arm.name)
        tags = [what for what, f in rules.items() if f == fam.name]
        if other_list is not None and arms["model-free baseline"] == fam.name:  # why it runs every seed
            tags.append("paper's model-free baseline")
        source = "" if fam.source == spec.name else f" by {fam.source}"
        lines.append(
            f"  # {fam.name}: {fam.arm.name} {fam.iqm:.4g}{source} ({others})" + (f"; the {' and '.join(tags)}" if tags else "")
        )
        entry: dict[str, Any] = {"method": fam.method}
        if fam.arm.match_updates:
            entry["match_updates"] = True
        if fam.arm.overrides:
            entry["overrides"] = fam.arm.overrides
        if other_list is not None and fam.name not in main:
            entry["seeds"] = other_list
        lines.append(f"  {fam.name}: {json_line(entry)}")
    lines += [f"overrides: {json_line(overrides)}", "outcome: holdout"]
    if thresholds:
        if by_rule:
            lines.append(f"# threshold {threshold:g} by docs/confirmatory.md's rule: {THRESHOLD_RULE}")
        lines.append(f"thresholds: {json_line(thresholds)}")
    lines.append(f"statistics: {json_line({'confidence': spec.confidence, 'reps': spec.reps})}")
    pairs = list(dict.fromkeys((h["better"], h["than"]) for h in hypotheses.values()))
    rl = [f.name for f in families if f.method not in CONTROL_METHODS]
    for controller in (arms["mpc"], arms["dpc"]):  # H4's pairs that are no hypothesis: compared all the same
        pairs += [(controller, arm) for arm in rl if controller and (controller, arm) not in pairs]
    if arms["mpc"] and arms["feedback"]:
        pairs.append((arms["mpc"], arms["feedback"]))
    lines.append("comparisons:")
    lines += [f"  - [{a}, {b}]" for a, b in pairs]
    lines.append("hypotheses:")
    lines += [f"  {hid}: {json_line(h)}" for hid, h in hypotheses.items()]
    if spec.record is not None:
        record_path = _relative(str(spec.record.path.parent / f"{name}.json"), folder)
    else:
        record_path = f"../results/{name}.json"
    lines.append(f"record: {{path: {record_path}, format: study}}")
    draft = _parsed(lines, where, folder)  # a draft that does not read is a bug
    plan = _plan(sources, draft, families, total_steps, tuned_steps, holdout_episodes)
    lines[-1:-1] = ["plan: >-", *_wrapped(plan, "  ")]
    _parsed(lines, where, folder)
    return "\n".join(lines) + "\n"


def _families(spec: StudySpec, record: dict[str, Any]) -> list[_Family]:
    """Each method's choice in tuning study ``spec`` (every candidate finished), from its report."""
    if not spec.tuning:
        raise ConfigError(f"{spec.name} is not a tuning study (no `tuning:`): a confirmatory draft needs each method's choice")
    if len(spec.systems) != 1 or spec.grid:
        raise ConfigError(f"{spec.name} tunes {len(spec.systems)} systems or a grid: a draft takes one system and no grid")
    groups = study_report(spec, record).stats["groups"]
    if len(groups) != 1:
        raise ConfigError(f"{spec.name}: its record has {len(groups)} groups of finished runs, a draft needs exactly one")
    group = next(iter(groups.values()))
    missing = [f for f, c in group.get("tuning", {}).items() if not c["chosen"]]
    if missing or "tuning_rules" not in group:
        raise ConfigError(
            f"{spec.name}: no choice yet for {', '.join(missing) or 'every method'} (runs missing or unfinished): "
            f"finish it first (`pimbrl study status`)"
        )
    families = [
        _Family(
            name,
            spec.arm(c["chosen"]),
            float(c["iqm"][c["chosen"]]),
            {a: float(v) for a, v in c["iqm"].items()},
            spec.name,
            group["arms"][c["chosen"]],
        )
        for name, c in group["tuning"].items()
    ]
    return families


def _check_amendment(spec: StudySpec, tuned: Any, amending: StudySpec) -> None:
    """A clear error where tuning study ``amending`` has not ``spec``'s system, overrides, real steps and budget."""
    theirs = _tuning_run_config(amending)
    why = None
    if amending.systems != spec.systems:
        why = f"tunes {amending.systems}, not {spec.systems}"
    elif amending.overrides != spec.overrides:
        why = f"has the overrides {json_line(amending.overrides)}, not {json_line(spec.overrides)}"
    elif theirs.total_steps != tuned.total_steps:
        why = f"runs {theirs.total_steps:,d} real steps, not {tuned.total_steps:,d}"
    elif amending.tuning_budget != spec.tuning_budget:
        why = f"gives each method {amending.tuning_budget} settings x seeds, not {spec.tuning_budget}"
    if why is not None:
        raise ConfigError(
            f"{amending.name} cannot amend {spec.name}: it {why}; an amendment re-tunes some methods of the same "
            "system with the same budget"
        )


#: how ``--threshold rule`` derives the steps-to-threshold return (stated before any study used it)
THRESHOLD_RULE = (
    "the lowest final validation IQM among the chosen settings of the arms H1a and H3 compare (PiMBRL, MBRL, "
    "known-scheme Dyna and the tuned model-free arm), rounded toward a worse return to two significant figures"
)


def rule_threshold(name: str, families: list[_Family], arms: dict[str, str | None]) -> float:
    """The threshold :data:`THRESHOLD_RULE` gives: every arm it names reached it, as an IQM, on validation."""
    import math

    named = {arms[r] for r in ("pimbrl", "mbrl", "known-scheme", "tuned model-free arm") if arms.get(r)}
    iqms = [f.iqm for f in families if f.name in named]
    if not iqms:
        raise ConfigError(f"{name}: no arm of H1a or H3 was tuned, so the threshold rule has nothing to read")
    low = min(iqms)
    if low == 0:
        return 0.0
    unit = 10.0 ** (math.floor(math.log10(abs(low))) - 1)
    return float(round(math.floor(low / unit + 1e-9) * unit, 10))


def _tuning_run_config(spec: StudySpec) -> Any:
    """The resolved configuration of the tuning study's first run (its budget and threshold are every run's)."""
    from .engine import plan_study

    return plan_study(spec, Path(spec.name))[0].config


def _parsed(lines: list[str], where: str, folder: Path) -> StudySpec:
    text = "\n".join(lines) + "\n"
    return parse_spec(load_yaml(text), where=where, base=folder, text=text)


#: the methods the protocol's hypotheses name, one arm each (the model-free arm is chosen by rule)
_NAMED = ("pimbrl", "mbrl", "known-scheme", "identified-scheme", "mpc", "dpc", "feedback")


def _protocol_arms(name: str, families: list[_Family], rules: dict[str, str | None], partial: bool) -> dict[str, str | None]:
    """The arm of each role the protocol names: a method's one family, the rules' arms, the best controller.

    Two families of one named method (two PiMBRL settings kept apart) are an error: which one a hypothesis
    means would be a choice the protocol does not make.
    """
    arms: dict[str, str | None] = {}
    for method in _NAMED:
        found = [f.name for f in families if f.method == method]
        if len(found) > 1:
            raise ConfigError(
                f"{name}: {', '.join(found)} all tune the method {method}; the protocol's hypotheses name one arm per "
                "method: write the confirmatory spec by hand, naming which"
            )
        arms[method] = found[0] if found else None
    controllers = [f for f in families if f.method in CONTROL_METHODS]
    arms["best controller"] = max(controllers, key=lambda f: f.iqm).name if controllers else None
    baseline = [f.name for f in families if _is_model_free_baseline(f.arm)]
    arms["model-free baseline"] = baseline[0] if len(baseline) == 1 else None
    arms["tuned model-free arm"] = None if partial else rules.get("tuned model-free arm")
    arms["best RL arm"] = None if partial else rules.get("best RL arm")
    if partial:  # under a wrong prior: H1 and H2 only (no controller with a wrong equation is in the protocol)
        arms.update({"mpc": None, "dpc": None, "best controller": None})
    else:
        arms["identified-scheme"] = None
    return arms


def _is_model_free_baseline(arm: Any) -> bool:
    """Whether ``arm`` is the paper's MFRL: the method mfrl with the recipe's agent and update ratio.

    That is TD3 at the recipe's updates per real step: not matched to the model-based budget, not CrossQ or REDQ.
    """
    return arm.method == "mfrl" and not arm.match_updates and not {"agent", "utd"} & set(arm.overrides)


def _hypotheses(
    name: str, families: list[_Family], arms: dict[str, str | None], threshold: float | None, main: set[str]
) -> dict[str, dict[str, Any]]:
    """The protocol's hypotheses (docs/confirmatory.md) among ``families``, in its order.

    ``main``: where some arms run fewer seeds, the arms that run the full number; an H4 pair with another
    arm would be inconclusive by rule, so it is left to the comparisons.
    """
    pimbrl, mbrl, known, identified = arms["pimbrl"], arms["mbrl"], arms["known-scheme"], arms["identified-scheme"]
    model_free = arms["tuned model-free arm"]
    if threshold is None and ((pimbrl and mbrl) or (known and model_free and not identified)):
        raise ConfigError(
            f"{name}: H1a and H3 count real steps to a threshold, and the system's recipe sets none: give "
            "--threshold T (chosen on earlier or validation curves, never on the holdout pool)"
        )
    t = f"{threshold:g}" if threshold is not None else ""
    steps = {"metric": "steps_to_threshold", "threshold": threshold}
    out: dict[str, dict[str, Any]] = {}
    if pimbrl and mbrl:
        out["H1a"] = {"claim": f"PiMBRL reaches {t} in fewer real steps than MBRL", "better": pimbrl, "than": mbrl, **steps}
        out["H1b"] = {"claim": "PiMBRL's final policy beats MBRL's on the holdout states", "better": pimbrl, "than": mbrl}
    if identified and mbrl:
        out["H2a"] = {"claim": "Dyna with the identified scheme beats data-only MBRL on the holdout states",
                      "better": identified, "than": mbrl}  # fmt: skip
    if identified and known:
        out["H2b"] = {"claim": "Dyna with the identified scheme beats the wrong prior's scheme held fixed on the "
                      "holdout states", "better": identified, "than": known}  # fmt: skip
    if known and model_free and not identified:
        out["H3"] = {"claim": f"Known-scheme Dyna reaches {t} in fewer real steps than the tuned model-free arm",
                     "better": known, "than": model_free, **steps}  # fmt: skip
    best = arms["best RL arm"]
    rl = [f.name for f in families if f.method not in CONTROL_METHODS]
    for hid, method, what in (
        ("H4a", "mpc", "MPC with the known equation"),
        ("H4b", "dpc", "DPC trained through the known equation"),
    ):
        controller = arms[method]
        if not controller or not best:
            continue
        out[hid] = {"claim": f"{what} beats the best RL arm ({best}) on the holdout states", "better": controller, "than": best}
        for arm in rl:
            if arm != best and (not main or arm in main):
                out[f"{hid}-{arm}"] = {"claim": f"{what} beats {arm} on the holdout states", "better": controller, "than": arm}
    return out


def _question(
    spec: StudySpec, system: str, families: list[_Family], hypotheses: dict[str, Any], episodes: int, sources: str
) -> str:
    settings, seeds = spec.tuning_budget
    wrong = f" with the prior {json_line(spec.overrides['model.prior'])}" if "model.prior" in spec.overrides else ""
    claims = "; ".join(f"{hid}: {h['claim']}" for hid, h in hypotheses.items())
    return (
        f"On {system}{wrong}, with each method's setting chosen on the validation draws by {sources} (equal "
        f"budgets: {settings} settings x {seeds} seed{'s' if seeds != 1 else ''}) and every run judged once on the "
        f"first {episodes} states of the holdout pool, which of these claims hold? {claims}."
    )


def _plan(
    sources: str,
    draft: StudySpec,
    families: list[_Family],
    total_steps: int | None,
    tuned_steps: int,
    episodes: int,
) -> str:
    """The compute plan: each arm's mean wall-clock in the tuning runs x its runs (two for a seed-free controller).

    Each run's holdout episodes are added at the arm's inference cost per control step in the tuning runs
    (MPC's minutes: on Allen-Cahn, 100 episodes of 100 steps at 86 ms a step are 14 of its 17 minutes a run).
    """
    from ..systems.registry import get_system
    from .engine import plan_study
    from .replicas import seed_free

    scale, scaled = 1.0, ""
    if total_steps is not None and total_steps != tuned_steps:
        scale = total_steps / tuned_steps
        scaled = f"; RL arms scaled by {scale:g} from the tuning runs' {tuned_steps:,d} steps to {total_steps:,d}"
    runs = plan_study(draft, Path(draft.name))
    parts, minutes = [], 0.0
    for fam in families:
        own = [r for r in runs if r.arm == fam.name]
        trained = min(len(own), 2) if own and seed_free(own[0]) else len(own)
        control = bool(own) and own[0].config.control  # a controller's cost follows its horizon, not the budget
        summary = fam.summary
        wall = (summary.get("wall_s") or 0.0) / 60 * (1.0 if control else scale)
        system = get_system(own[0].system) if own else None
        if system is not None and summary.get("inference_s_per_step"):
            wall += summary["inference_s_per_step"] * system.episode_steps * episodes / 60
        parts.append(f"{fam.name} {wall:.1f}")
        minutes += trained * wall
    return (
        f"{len(runs)} runs ({len(families)} arms), minutes per run from {sources}'s runs (one of two processes"
        f"{scaled}), with {episodes} holdout episodes each at the arm's inference cost per control step: "
        f"{', '.join(parts)}; a seed-free controller trains two "
        f"seeds: about {minutes:,.0f} CPU-minutes, {minutes / 2:,.0f} minutes with two processes (--jobs 2); "
        "resumed across sessions"
    )


def _relative(path: str, folder: Path) -> str:
    """``path`` (a module name, or a file) as the new spec names it: a file relative to its folder."""
    if not path.endswith(".py") and not path.endswith(".json"):
        return path
    return os.path.relpath(path, folder)


def _wrapped(text: str, indent: str, width: int = 110) -> list[str]:
    """``text`` as lines of a YAML folded block (``>-``)."""
    lines, line = [], ""
    for word in text.split():
        if line and len(line) + 1 + len(word) > width:
            lines.append(indent + line)
            line = word
        else:
            line = f"{line} {word}" if line else word
    if line:
        lines.append(indent + line)
    return lines
