"""Fuzzing run directories (issue 32): hundreds of malformed runs, four readers each, no traceback, hang or escape.

Every case is a copy of one finished tiny run with one thing wrong: a file missing, empty, cut short,
garbage, a symbolic link (to a file or folder outside the run, to /dev/zero), a FIFO, a folder, a hard
link to a file outside, a sparse file beyond the size bound; a top-level field of config.json of the wrong
type or non-finite; a configuration field of the wrong type, an env id in Gymnasium's ``module:id`` form
(naming a planted module) or unregistered; a CSV cell that is not a finite number, a row of the wrong
width, a damaged header. On each, ``pimbrl eval``, ``resume``, ``plot`` and ``compare --no-run`` must end
with exit status 0 or with status 2 and one error line, within 10 s, without a traceback, without
importing the planted module and without touching any file outside the run directory (the plot and the
comparison's summary go where the command was told to write them). docs/training.md reports the count.
"""

from __future__ import annotations

import contextlib
import hashlib
import io
import json
import os
import shutil
import sys
from collections.abc import Callable
from pathlib import Path

import pytest

from pimbrl.cli import main

from .test_hostile_rundirs import within
from .test_run_safety import ARGS

pytestmark = [pytest.mark.slow, pytest.mark.filterwarnings("ignore::UserWarning")]

Mutation = Callable[[Path, Path], None]  # (run directory, the folder outside it) -> None
PLANTED = "pimbrl_fuzz_planted"


def _file_mutations(name: str) -> dict[str, Mutation]:
    def delete(run: Path, out: Path) -> None:
        target = run / name
        if target.is_dir() and not target.is_symlink():
            shutil.rmtree(target)
        elif target.exists() or target.is_symlink():
            target.unlink()

    def replaced(make: Callable[[Path, Path], None]) -> Mutation:
        def mutate(run: Path, out: Path) -> None:
            delete(run, out)
            make(run / name, out)

        return mutate

    def cut(run: Path, out: Path) -> None:
        data = (run / name).read_bytes()
        (run / name).write_bytes(data[: len(data) // 2])

    def garbage(run: Path, out: Path) -> None:
        seed = int(hashlib.sha256(name.encode()).hexdigest()[:8], 16)
        (run / name).write_bytes(bytes((seed * (i + 7) * 2654435761) % 256 for i in range(4096)))

    def sparse(run: Path, out: Path) -> None:
        with open(run / name, "ab") as fh:
            fh.truncate(80 << 30)  # 80 GB of holes: beyond every size bound, costs no disk

    return {
        "missing": delete,
        "empty": replaced(lambda p, out: p.write_bytes(b"")),
        "cut short": cut,
        "garbage": garbage,
        "symlink to a file outside": replaced(lambda p, out: p.symlink_to(out / "victim.txt")),
        "symlink to /dev/zero": replaced(lambda p, out: p.symlink_to("/dev/zero")),
        "symlink to a folder outside": replaced(lambda p, out: p.symlink_to(out / "folder")),
        "dangling symlink": replaced(lambda p, out: p.symlink_to(out / "nothing-here")),
        "fifo": replaced(lambda p, out: os.mkfifo(p)),
        "folder": replaced(lambda p, out: p.mkdir()),
        "hard link to a file outside": replaced(lambda p, out: os.link(out / "victim.txt", p)),
        "sparse 80 GB": sparse,
    }


def _json_mutations() -> dict[str, Mutation]:
    def set_field(path: list[str], value: object, raw: str | None = None) -> Mutation:
        def mutate(run: Path, out: Path) -> None:
            payload = json.loads((run / "config.json").read_text())
            node = payload
            for key in path[:-1]:
                node = node[key]
            node[path[-1]] = "@RAW@" if raw is not None else value
            text = json.dumps(payload)
            if raw is not None:
                text = text.replace('"@RAW@"', raw)
            (run / "config.json").write_text(text)

        return mutate

    def drop(path: list[str]) -> Mutation:
        def mutate(run: Path, out: Path) -> None:
            payload = json.loads((run / "config.json").read_text())
            node = payload
            for key in path[:-1]:
                node = node[key]
            node.pop(path[-1], None)
            (run / "config.json").write_text(json.dumps(payload))

        return mutate

    values: dict[str, tuple[object, str | None]] = {
        "null": (None, None),
        "0": (0, None),
        "-1": (-1, None),
        "1e308": (1e308, None),
        "a string": ("x", None),
        "a list": ([1, "a"], None),
        "an object": ({"a": 1}, None),
        "true": (True, None),
        "NaN": (None, "NaN"),
        "Infinity": (None, "-Infinity"),
        "1e999": (None, "1e999"),
        "a 400-digit integer": (None, "1" + "0" * 400),
    }
    out: dict[str, Mutation] = {}
    for key in ("status", "config", "versions", "summary", "command"):
        out[f"config.json {key} missing"] = drop([key])
        for label, (value, raw) in values.items():
            out[f"config.json {key} = {label}"] = set_field([key], value, raw)
    for env in (7, "", f"{PLANTED}:pimbrl/Pendulum-v0", "nobody/Nothing-v0", None, ["pimbrl/Pendulum-v0"], "CarRacing-v3"):
        out[f"config.env = {env!r}"] = set_field(["config", "env"], env)
    out["config.env missing"] = drop(["config", "env"])
    for key in ("method", "agent", "seed", "total_steps", "eval_episodes", "threshold", "eval_seed"):
        for label in ("null", "a string", "-1", "1e308", "a list", "true", "Infinity"):
            value, raw = values[label]
            out[f"config.{key} = {label}"] = set_field(["config", key], value, raw)
    out["config.agent.hidden = [0]"] = set_field(["config", "agent", "hidden"], [0])
    out["config.agent.hidden = [1e9]"] = set_field(["config", "agent", "hidden"], [10**9])
    out["config.agent = []"] = set_field(["config", "agent"], [])
    out["summary.wall_s = null"] = set_field(["summary", "wall_s"], None)
    out["summary.wall_s = a 400-digit integer"] = set_field(["summary", "wall_s"], None, "1" + "0" * 400)
    out["config.threshold = a 400-digit integer"] = set_field(["config", "threshold"], None, "1" + "0" * 400)
    return out


def _csv_mutations() -> dict[str, Mutation]:
    def cell(name: str, column: str, value: str, row: int = 1) -> Mutation:
        def mutate(run: Path, out: Path) -> None:
            lines = (run / name).read_text().splitlines()
            header = lines[0].split(",")
            cells = lines[row].split(",")
            cells[header.index(column)] = value
            lines[row] = ",".join(cells)
            (run / name).write_text("\n".join(lines) + "\n")

        return mutate

    def lines_edit(name: str, edit: Callable[[list[str]], list[str]], end: str = "\n") -> Mutation:
        def mutate(run: Path, out: Path) -> None:
            lines = (run / name).read_text().splitlines()
            (run / name).write_text("\n".join(edit(lines)) + end)

        return mutate

    out: dict[str, Mutation] = {}
    for value in ("inf", "-inf", "nan", "-1", "1e300", "abc", "", "1.5", "1e400", "0x10"):
        out[f"evaluations.csv step = {value!r}"] = cell("evaluations.csv", "step", value)
    for column in ("return_mean", "return_min", "updates", "wall_s"):
        for value in ("nan", "inf", "", "x", "1e400"):
            out[f"evaluations.csv {column} = {value!r}"] = cell("evaluations.csv", column, value, row=2)
    for value in ("inf", "nan", "-5", "x"):
        out[f"episodes.csv step = {value!r}"] = cell("episodes.csv", "step", value)
    for name in ("evaluations.csv", "episodes.csv", "metrics.csv"):
        out[f"{name}: a row with an extra field"] = lines_edit(name, lambda ls: [*ls[:1], ls[1] + ",7", *ls[2:]])
        out[f"{name}: a row with a field missing"] = lines_edit(name, lambda ls: [*ls[:1], ls[1].rsplit(",", 1)[0], *ls[2:]])
        out[f"{name}: header only"] = lines_edit(name, lambda ls: ls[:1])
        out[f"{name}: header renamed"] = lines_edit(name, lambda ls: [ls[0].replace("step", "stop"), *ls[1:]])
        out[f"{name}: a byte-order mark"] = lines_edit(name, lambda ls: ["\ufeff" + ls[0], *ls[1:]])
        out[f"{name}: no final newline"] = lines_edit(name, lambda ls: ls, end="")
        out[f"{name}: a NUL byte"] = lines_edit(name, lambda ls: [*ls[:1], ls[1] + "\0", *ls[2:]])
        out[f"{name}: a 2 MB line"] = lines_edit(name, lambda ls: [*ls, "9" * (2 << 20)])
        out[f"{name}: not UTF-8"] = lambda run, out, name=name: (run / name).write_bytes(b"\xff\xfe\x00step\n\x80\x81\n")
    return out


def _folder_mutations() -> dict[str, Mutation]:
    def checkpoints_elsewhere(run: Path, out: Path) -> None:
        shutil.copytree(run / "checkpoints", out / "folder" / "copied", dirs_exist_ok=True)
        shutil.rmtree(run / "checkpoints")
        (run / "checkpoints").symlink_to(out / "folder" / "copied")

    def checkpoints_a_file(run: Path, out: Path) -> None:
        shutil.rmtree(run / "checkpoints")
        (run / "checkpoints").write_text("not a folder")

    def checkpoints_a_fifo(run: Path, out: Path) -> None:
        shutil.rmtree(run / "checkpoints")
        os.mkfifo(run / "checkpoints")

    def tb_elsewhere(run: Path, out: Path) -> None:
        (run / "tb").symlink_to(out / "folder")

    def running(run: Path, out: Path) -> None:  # resume then trains (the run is otherwise valid)
        payload = json.loads((run / "config.json").read_text())
        payload["status"] = "running"
        payload["config"]["total_steps"] = 300
        (run / "config.json").write_text(json.dumps(payload))

    return {
        "checkpoints is a link to a folder outside": checkpoints_elsewhere,
        "checkpoints is a file": checkpoints_a_file,
        "checkpoints is a fifo": checkpoints_a_fifo,
        "tb is a link to a folder outside": tb_elsewhere,
        "valid, running, 100 steps to go": running,
    }


def all_mutations() -> dict[str, Mutation]:
    cases: dict[str, Mutation] = {}
    for name in ("config.json", "evaluations.csv", "episodes.csv", "metrics.csv", "checkpoints/latest.pt", "run.lock"):
        cases.update({f"{name}: {label}": m for label, m in _file_mutations(name).items()})
    cases.update(_json_mutations())
    cases.update(_csv_mutations())
    cases.update(_folder_mutations())
    return cases


def _snapshot(folder: Path) -> dict[str, str]:
    """Every entry under ``folder`` with its kind and contents' digest (links not followed)."""
    seen = {}
    for path in sorted(folder.rglob("*")):
        info = path.lstat()
        if path.is_symlink():
            seen[str(path)] = f"link {os.readlink(path)}"
        elif path.is_file():
            seen[str(path)] = f"file {hashlib.sha256(path.read_bytes()).hexdigest()} {info.st_mtime_ns}"
        else:
            seen[str(path)] = f"other {info.st_mode:o}"
    return seen


def test_at_least_200_cases() -> None:
    assert len(all_mutations()) >= 200


SHARDS = 4  # the cases are split so that the test processes share them (36 to 40 s a shard beside two training processes)


@pytest.fixture(scope="module")
def fuzz_base(tmp_path_factory) -> Path:
    """A folder with one finished tiny run (``template``) and a module to plant (``planted``), per test process."""
    base = tmp_path_factory.mktemp("fuzz")
    assert main(["train", *ARGS, "--run-dir", str(base / "template")]) == 0
    (base / "planted").mkdir()
    (base / "planted" / f"{PLANTED}.py").write_text(f"open({str(base / 'imported')!r}, 'w').close()\n")
    return base


@pytest.mark.parametrize("shard", range(SHARDS))
def test_malformed_run_directories_give_no_traceback_hang_or_escape(shard: int, fuzz_base: Path) -> None:
    base = fuzz_base
    template = base / "template"
    planted = base / "planted"
    marker = base / "imported"
    sys.path.insert(0, str(planted))
    problems: list[str] = []
    counts = {"cases": 0, "commands": 0, "exit 0": 0, "exit 2": 0}
    cases = list(enumerate(all_mutations().items()))[shard::SHARDS]
    try:
        for i, (label, mutate) in cases:
            case = base / f"case{i}"
            root = case / "C"
            run = root / "mfrl" / "seed0"
            outside = case / "outside"
            (outside / "folder").mkdir(parents=True)
            (outside / "victim.txt").write_text("step,return_mean\n1,2\n")
            (outside / "folder" / ".latest.pt.abc123.tmp").write_bytes(b"someone's file")
            shutil.copytree(template, run)
            mutate(run, outside)
            before = _snapshot(outside)
            counts["cases"] += 1
            commands = {
                "eval": ["eval", str(run), "--episodes", "1"],
                "resume": ["resume", str(run), "--quiet"],
                "plot": ["plot", str(run), "--out", str(case / "plot" / "curves.png")],
                "compare": ["compare", "pendulum", "--methods", "mfrl", "--seeds", "1", "--run-dir", str(root), "--no-run"],
            }
            for name, argv in commands.items():
                counts["commands"] += 1
                err = io.StringIO()
                try:
                    with within(10), contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
                        code = main(argv)
                except BaseException as exc:  # a traceback (or a hang) the user would have seen
                    problems.append(f"{label} / {name}: {type(exc).__name__}: {exc}")
                    continue
                text = err.getvalue()
                errors = [line for line in text.splitlines() if "error:" in line]
                if "Traceback" in text or code not in (0, 2) or (code == 2 and len(errors) != 1):
                    problems.append(f"{label} / {name}: exit {code}, stderr {text[-300:]!r}")
                counts[f"exit {code}"] = counts.get(f"exit {code}", 0) + 1
                if marker.exists():
                    problems.append(f"{label} / {name}: imported the module named in config.json")
                    marker.unlink()
            if _snapshot(outside) != before:
                problems.append(f"{label}: a file outside the run directory was touched")
            shutil.rmtree(case, ignore_errors=True)
    finally:
        sys.path.remove(str(planted))
    print(f"fuzzed run directories, shard {shard + 1} of {SHARDS}: {counts}")
    assert counts["cases"] == len(cases)
    assert not problems, "\n".join(problems[:40])
