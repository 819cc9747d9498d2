"""Bring your own system (issue 28): a system declared once, outside the library, with the whole method on it.

A third system is declared in this file alone (no library code edited) and trained; the two examples train
through the command line with ``--import``; a run records what it imported and refuses to reopen without it;
installed packages' entry points register systems; bad declarations and bad coefficients are one-line errors.
"""

from __future__ import annotations

import json
import re
import subprocess
import sys
import textwrap
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import torch
from gymnasium.utils.env_checker import check_env

from pimbrl.cli import main
from pimbrl.physics import Stencil
from pimbrl.systems import (
    Coefficient,
    FourierOperator,
    ODESystem,
    PeriodicPDESystem,
    SystemSpecError,
    declare,
    get_system,
    import_systems,
    resolve_env_id,
    xp_of,
)

from .test_training import TINY

ROOT = Path(__file__).resolve().parents[1]
DUFFING = str(ROOT / "examples" / "duffing.py")
ALLEN_CAHN = str(ROOT / "examples" / "allen_cahn.py")


class VanDerPol(ODESystem):
    """A forced Van der Pol oscillator (three RK4 steps per control step), declared in a test file."""

    name = "vanderpol"
    state_dim = 2
    action_low, action_high = [-1.0], [1.0]
    dt, substeps = 0.05, 3
    episode_steps = 50
    divergence_bound = 20.0
    coefficients = {"mu": Coefficient(1.0, low=0.0, high=5.0)}  # noqa: RUF012 - the API's form

    def rhs(self, u, a):
        xp = xp_of(u)
        x, v = u[..., 0], u[..., 1]
        return xp.stack([v, self.mu * (1 - x**2) * v - x + a[..., 0]], -1)

    def reward(self, u, a, u_next, k, path=None):
        return -(u_next**2).sum(-1)

    def initial_states(self, rng, n):
        return rng.uniform(-1.0, 1.0, size=(n, 2))


@pytest.fixture(scope="module")
def vanderpol() -> str:
    system = declare(VanDerPol, "test/VanDerPol-v0", aliases=("vanderpol",))
    return system.id


def test_a_third_system_from_this_file_alone_trains_with_pimbrl(vanderpol: str, tmp_path) -> None:
    run = tmp_path / "run"
    flags = ["--steps", "240", "--warmup-steps", "60", "--update-after", "60", "--eval-every", "120", "--eval-episodes", "2"]
    flags += ["--model.start-after", "60", "--physics.start-after", "60", "--imagine.rollout-length", "5"]
    assert main(["train", "vanderpol", "--method", "pimbrl", *flags, "--run-dir", str(run), *TINY]) == 0
    payload = json.loads((run / "config.json").read_text())
    assert payload["status"] == "finished" and payload["system"] == {"id": vanderpol, "origin": f"module {__name__}"}
    # config.json records the model that trained: an MLP emitting one state per solver step, checked by the solver
    method = payload["config"]["method"]
    assert (method["network"], method["scheme"], method["n_intermediate"]) == ("mlp", "solver", 3)
    metrics = (run / "metrics.csv").read_text().splitlines()
    header = metrics[0].split(",")
    physics = [row.split(",")[header.index("model/physics_loss")] for row in metrics[1:]]
    assert any(value not in ("", "nan") and float(value) > 0 for value in physics)  # the physics loss was trained


def test_a_declared_ode_is_a_checked_gymnasium_env_with_disjoint_draws(vanderpol: str) -> None:
    env = gym.make(vanderpol)
    check_env(env.unwrapped, skip_render_check=True)
    task = env.unwrapped.task
    assert resolve_env_id("vanderpol") == vanderpol and task.max_episode_steps == 50
    validation, test = task.validation_initial_states(8), task.test_initial_states(8, seed=0)
    assert not (validation[:, None, :] == test[None, :, :]).all(-1).any()
    vector = gym.make_vec(vanderpol, num_envs=3, vectorization_mode="vector_entry_point")
    obs, _ = vector.reset(seed=1)
    assert obs.shape == (3, 2)


def test_the_residual_of_a_true_step_of_a_declared_ode_vanishes(vanderpol: str) -> None:
    from pimbrl.models import PhysicsResidual, make_model

    phys = VanDerPol()
    u = torch.randn(16, 2, dtype=torch.float64)
    a = torch.rand(16, 1, dtype=torch.float64) * 2 - 1
    path = torch.stack([phys.step(u, a, substeps=k) for k in (1, 2, 3)], dim=1)
    residual = PhysicsResidual(phys, PhysicsResidual.states_per_step(phys, 5))
    assert residual.n == 3 and float(residual.loss(u, path, a)) < 1e-24
    model = make_model(phys)
    assert model(u.float(), a.float()).shape == (16, 3, 2)  # the MLP emits the three solver steps
    np_u = u.numpy()
    np.testing.assert_allclose(phys.advance(np_u, a.numpy(), np.zeros(16))[0], phys.step(u, a).numpy(), rtol=0, atol=1e-15)


def test_learned_coefficients_of_a_declared_ode_are_fitted(vanderpol: str) -> None:
    from pimbrl.models import PhysicsResidual

    true, prior = VanDerPol(mu=1.6), VanDerPol(mu=1.0)
    u = torch.randn(64, 2, dtype=torch.float64)
    a = torch.rand(64, 1, dtype=torch.float64) * 2 - 1
    u1 = true.step(u, a)
    residual = PhysicsResidual(prior, 3, scheme="solver", learned={"mu": (0.0, 5.0)})
    opt = torch.optim.Adam(residual.coefficients.parameters(), lr=0.05)
    for _ in range(300):
        opt.zero_grad()
        residual.coefficient_loss(u, a, u1).backward()
        opt.step()
    assert abs(residual.coefficients.named_values()["mu"] - 1.6) < 0.02


class Diffusion(PeriodicPDESystem):
    """Forced heat equation on [0, 1) given by its Fourier symbol (a linear PDE: N(u) = 0)."""

    name = "heat"
    n, length = 32, 1.0
    dt, substeps = 1e-3, 10
    action_low, action_high = [-1.0, -1.0], [1.0, 1.0]
    episode_steps = 20
    divergence_bound = 10.0
    reflection_symmetric = True
    coefficients = {"kappa": Coefficient(0.01, low=0.0, high=1.0)}  # noqa: RUF012

    def linear_operator(self):
        d2 = Stencil.centered((1.0, -2.0, 1.0)).scaled(self.kappa / self.dx**2)
        return FourierOperator(d2.symbol(self.n))

    def nonlinearity(self, u):
        return 0.0 * u

    def actuators(self):
        return np.stack([np.sin(2 * np.pi * self.x), np.cos(2 * np.pi * self.x)])

    def reward(self, u, a, u_next, k, path=None):
        return -(u_next**2).mean(-1)

    def initial_states(self, rng, n):
        return rng.normal(0.0, 0.3, size=(n, 1)) * np.sin(2 * np.pi * self.x)[None, :]


def test_a_fourier_symbol_is_the_same_operator_as_its_stencil() -> None:
    heat = Diffusion()
    stencil = Stencil.centered((1.0, -2.0, 1.0)).scaled(heat.kappa / heat.dx**2)
    u = np.random.default_rng(0).normal(size=(3, 32))
    np.testing.assert_allclose(heat.linear.apply(u), stencil.apply(u), atol=1e-10)
    np.testing.assert_allclose(heat.linear.apply(torch.as_tensor(u)).numpy(), stencil.apply(u), atol=1e-10)
    etd = heat.etdrk4(1)  # the coarse step of the physics loss, from the symbol
    v = torch.as_tensor(u)
    np.testing.assert_allclose(etd.step(v, lambda w: 0 * w).numpy(), heat.step(u, np.zeros((3, 2))), atol=1e-6)


def test_the_examples_are_short_and_declare_their_systems() -> None:
    for path in (DUFFING, ALLEN_CAHN):
        code = [line for line in Path(path).read_text().splitlines() if line.strip() and not line.strip().startswith("#")]
        body = [line for line in code if not line.strip().startswith(('"""', "'''"))]
        assert len(body) <= 80, (path, len(body))
    ids = import_systems([DUFFING, ALLEN_CAHN])
    assert ids == ["example/Duffing-v0", "example/AllenCahn-v0"]  # what the two files registered (again or not)
    for alias, env_id in (("duffing", "example/Duffing-v0"), ("allen-cahn", "example/AllenCahn-v0")):
        assert resolve_env_id(alias) == env_id
        env = gym.make(env_id)
        check_env(env.unwrapped, skip_render_check=True)
        assert get_system(env_id).origin == f"--import {DUFFING if 'Duffing' in env_id else ALLEN_CAHN}"


@pytest.mark.slow
@pytest.mark.parametrize(("example", "alias"), [(DUFFING, "duffing"), (ALLEN_CAHN, "allen-cahn")])
@pytest.mark.parametrize("method", ["mfrl", "mbrl", "pimbrl"])
def test_the_examples_train_through_the_command_line(example: str, alias: str, method: str, tmp_path) -> None:
    run = tmp_path / "run"
    flags = ["--steps", "200", "--warmup-steps", "60", "--update-after", "60", "--eval-every", "100", "--eval-episodes", "2"]
    if method != "mfrl":
        flags += ["--model.start-after", "60"]
    cmd = [sys.executable, "-m", "pimbrl.cli", "train", alias, "--import", example, "--method", method, *flags]
    out = subprocess.run([*cmd, "--run-dir", str(run), *TINY], capture_output=True, text=True, cwd=tmp_path, timeout=600)
    assert out.returncode == 0, out.stderr
    assert "has no preset" not in out.stderr  # both examples declare one
    payload = json.loads((run / "config.json").read_text())
    assert payload["status"] == "finished" and payload["system"]["origin"] == f"--import {example}"
    if method != "pimbrl":
        return
    # reopening the run needs the same --import: without it, one line that says which to pass
    eval_cmd = [sys.executable, "-m", "pimbrl.cli", "eval", str(run), "--episodes", "1"]
    bare = subprocess.run(eval_cmd, capture_output=True, text=True, cwd=tmp_path, timeout=600)
    assert bare.returncode == 2 and bare.stderr.count("\n") == 1 and f"pass `--import {example}`" in bare.stderr
    ok = subprocess.run([*eval_cmd, "--import", example], capture_output=True, text=True, cwd=tmp_path, timeout=600)
    assert ok.returncode == 0, ok.stderr


@pytest.mark.slow  # a few seconds: the whole suite runs it, the fast tier does not
def test_resume_without_the_import_is_a_one_line_error_naming_it(tmp_path) -> None:
    code = textwrap.dedent(
        f"""
        import sys
        from pimbrl.cli import main
        sys.exit(main(["resume", {str(tmp_path / "run")!r}, "--quiet"]))
        """
    )
    # the module the run names, planted beside it: importing it would leave a marker
    (tmp_path / "my_system.py").write_text("open('IMPORTED', 'w').close()\n")
    run = tmp_path / "run"
    run.mkdir()
    payload = {
        "status": "running",
        "config": {"env": "example/Nowhere-v0"},
        "system": {"id": "example/Nowhere-v0", "origin": "--import my_system.py"},
    }
    (run / "config.json").write_text(json.dumps(payload))
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, cwd=tmp_path)
    assert out.returncode == 2 and out.stderr.count("\n") == 1
    assert "example/Nowhere-v0 is not registered here; pass `--import my_system.py` as its config.json records" in out.stderr
    assert not (tmp_path / "IMPORTED").exists()  # nothing named in the run directory was imported
    # an origin that is not of a known one-line form is not repeated
    payload["system"]["origin"] = "--import x.py\x1b[2J; rm -rf"
    (run / "config.json").write_text(json.dumps(payload))
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, cwd=tmp_path)
    assert out.returncode == 2 and "rm -rf" not in out.stderr and "\x1b" not in out.stderr


@pytest.mark.parametrize(
    ("spec", "message"),
    [
        ("no/such/file.py", "--import no/such/file.py: no such file"),
        ("no_such_module_xyz", "--import no_such_module_xyz: no module named 'no_such_module_xyz'"),
    ],
)
def test_a_bad_import_is_a_one_line_error(spec: str, message: str, capsys) -> None:
    assert main(["simulate", "pendulum", "--import", spec]) == 2
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1


def test_a_module_that_raises_on_import_is_a_one_line_error(tmp_path, capsys) -> None:
    bad = tmp_path / "broken.py"
    bad.write_text("raise RuntimeError('the user module is broken')\n")
    assert main(["simulate", "pendulum", "--import", str(bad)]) == 2
    err = capsys.readouterr().err
    assert "failed: RuntimeError: the user module is broken" in err and err.count("\n") == 1


@pytest.mark.slow
def test_an_installed_package_registers_its_systems_through_an_entry_point(tmp_path) -> None:
    pkg = tmp_path / "site"
    (pkg / "mysystems").mkdir(parents=True)
    (pkg / "mysystems" / "__init__.py").write_text(
        textwrap.dedent(
            f"""
            import importlib.util
            spec = importlib.util.spec_from_file_location("duffing_example", {DUFFING!r})
            module = importlib.util.module_from_spec(spec)
            spec.loader.exec_module(module)
            SYSTEM = module.SYSTEM
            """
        )
    )
    dist = pkg / "mysystems-1.0.dist-info"
    dist.mkdir()
    (dist / "METADATA").write_text("Metadata-Version: 2.1\nName: mysystems\nVersion: 1.0\n")
    (dist / "entry_points.txt").write_text("[pimbrl.systems]\nduffing = mysystems:SYSTEM\n")
    code = "from pimbrl.systems import load_entry_points, get_system; print(load_entry_points()); print(get_system('example/Duffing-v0').origin)"
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, env={"PYTHONPATH": f"{pkg}:{ROOT / 'src'}"}, timeout=120
    )
    assert out.returncode == 0, out.stderr
    assert out.stdout.split("\n")[:2] == ["['example/Duffing-v0']", "entry point duffing"]


@pytest.mark.slow
def test_an_import_by_a_relative_path_from_the_working_directory(tmp_path) -> None:
    cmd = [
        sys.executable,
        "-m",
        "pimbrl.cli",
        "simulate",
        "duffing",
        "--import",
        "examples/duffing.py",
        "--out",
        str(tmp_path / "d.png"),
    ]
    out = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert out.returncode == 0, out.stderr
    assert "example/Duffing-v0" in out.stdout


def test_a_missing_dependency_of_an_imported_module_is_named_as_such(tmp_path, monkeypatch, capsys) -> None:
    (tmp_path / "mysys_ext.py").write_text("import mysys\n")
    monkeypatch.chdir(tmp_path)
    assert main(["simulate", "pendulum", "--import", "mysys_ext"]) == 2
    err = capsys.readouterr().err
    assert "--import mysys_ext failed: ModuleNotFoundError: No module named 'mysys'" in err


def test_an_alias_cannot_shadow_a_gymnasium_id() -> None:
    with pytest.raises(SystemSpecError, match="the alias 'pendulum-v1' is a registered Gymnasium id"):
        declare(VanDerPol, "test/Shadow-v0", aliases=("pendulum-v1",))
    assert resolve_env_id("Pendulum-v1") == "Pendulum-v1"


def test_two_declarations_cannot_share_an_id(vanderpol: str, tmp_path) -> None:
    other = tmp_path / "other_vdp.py"
    other.write_text(
        "from tests.test_systems import VanDerPol\nfrom pimbrl.systems import declare\ndeclare(VanDerPol, 'test/VanDerPol-v0')\n"
    )
    with pytest.raises(SystemSpecError, match=re.escape("test/VanDerPol-v0 is already declared by module tests.test_systems")):
        import_systems([str(other)])


def test_one_file_imported_as_a_module_and_by_its_path_declares_one_system(tmp_path, monkeypatch) -> None:
    """`import my_systems` in a session, then a study's `imports: [my_systems.py]`: the same declaration again."""
    (tmp_path / "twice_vdp.py").write_text(
        "from tests.test_systems import VanDerPol\nfrom pimbrl.systems import declare\n\n\n"
        "class TwiceVdP(VanDerPol):\n    pass\n\n\ndeclare(TwiceVdP, 'test/TwiceVdP-v0')\n"
    )
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.delitem(sys.modules, "twice_vdp", raising=False)
    import_systems(["twice_vdp"])  # by module name: declared by the module's file
    assert import_systems([str(tmp_path / "twice_vdp.py")]) == ["test/TwiceVdP-v0"]  # by path: the same file
    assert resolve_env_id("test/TwiceVdP-v0") == "test/TwiceVdP-v0"
    other = tmp_path / "elsewhere" / "twice_vdp.py"  # a file of the same name elsewhere is another declaration
    other.parent.mkdir()
    other.write_text((tmp_path / "twice_vdp.py").read_text())
    with pytest.raises(SystemSpecError, match="test/TwiceVdP-v0 is already declared by"):
        import_systems([str(other)])


@pytest.mark.parametrize(
    ("attrs", "message"),
    [
        ({"coefficients": ("k",)}, "coefficients must be a dict of name -> Coefficient"),
        ({"coefficients": {"dt": Coefficient(0.1)}}, "'dt' cannot name a coefficient"),
        ({"action_low": [1.0], "action_high": [-1.0]}, "each action needs finite bounds with action_low < action_high"),
        ({"dt": float("nan")}, "dt must be a finite number > 0, got nan"),
        ({"action_low": [-1.0, -1.0]}, "action_low and action_high need one bound per action"),
    ],
)
def test_a_declaration_that_cannot_work_is_a_one_line_error(attrs, message) -> None:
    def build():
        cls = type("Broken", (VanDerPol,), dict(attrs))
        return cls()

    with pytest.raises(SystemSpecError, match=re.escape(message)):
        build()


def test_bad_declarations_are_one_line_errors() -> None:
    with pytest.raises(SystemSpecError, match="must look like 'namespace/Name-v0'"):
        declare(VanDerPol, "VanDerPol")
    with pytest.raises(SystemSpecError, match="is a built-in system of pimbrl"):
        declare(VanDerPol, "pimbrl/Burgers-v0")
    with pytest.raises(SystemSpecError, match="the alias 'burgers' already names pimbrl/Burgers-v0"):
        declare(VanDerPol, "test/Other-v0", aliases=("burgers",))
    with pytest.raises(SystemSpecError, match=r"default 7\.0 must be finite and in"):
        Coefficient(7.0, low=0.0, high=5.0)


@pytest.mark.parametrize(
    ("env_id", "kwargs", "message"),
    [
        ("test/VanDerPol-v0", {"mu": 9.0}, "vanderpol: coefficient mu must be a finite number in [0, 5], got 9.0"),
        ("test/VanDerPol-v0", {"mu": "1"}, "vanderpol: coefficient mu must be a number, got '1'"),
        ("test/VanDerPol-v0", {"nu": 1.0}, "vanderpol has no coefficient 'nu'; its coefficients are: mu"),
        # the list: each was a ZeroDivisionError, an OverflowError or a late "solver unstable"
        ("pimbrl/Burgers-v0", {"actuator_width": 1e-300}, "burgers: actuator_width must be a finite number in [0.001, 1]"),
        ("pimbrl/Burgers-v0", {"nu": 1e300}, "burgers: nu must be a finite number in [0, 1], got 1e+300"),
        ("pimbrl/Pendulum-v0", {"l": 1.7e308}, "Pendulum: l must be a finite number in (0, 1000], got 1.7e+308"),
        ("pimbrl/CartPole-v0", {"gravity": 1e6}, "CartPole: gravity must be a finite number in [-100, 100], got 1000000.0"),
        ("pimbrl/KuramotoSivashinsky-v0", {"actuator_width": 1e-300}, "ks: actuator_width must be a finite number in [0.01, 30]"),
    ],
)
def test_coefficients_outside_their_declared_bounds_are_one_line_errors(vanderpol, env_id, kwargs, message) -> None:
    with pytest.raises(ValueError, match=re.escape(message)) as info:
        gym.make(env_id, **kwargs)
    assert "\n" not in str(info.value)


def test_reset_options_that_are_not_a_dict_are_a_clear_error(vanderpol: str) -> None:
    for env_id in (vanderpol, "pimbrl/Pendulum-v0"):
        env = gym.make(env_id)
        with pytest.raises(TypeError, match=r"reset\(options=...\) must be a dict"):
            env.reset(options="x")


def test_a_system_without_a_preset_is_told_so_at_start(vanderpol: str, tmp_path, capsys) -> None:
    assert main(["train", "vanderpol", "--print-config"]) == 0
    err = capsys.readouterr().err
    assert "test/VanDerPol-v0 has no preset: the generic defaults of every setting apply" in err
    assert main(["train", "pendulum", "--print-config"]) == 0
    assert "has no preset" not in capsys.readouterr().err


def test_a_preset_given_as_a_mapping_is_the_same_recipes_as_its_file() -> None:
    """`declare(..., preset={...})` holds what a preset file holds (examples/allen_cahn.yaml, read as a mapping)."""
    from pimbrl.config import load_yaml

    path = ROOT / "examples" / "allen_cahn.yaml"
    as_file = declare(VanDerPol, "test/PresetFile-v0", preset=path)
    as_mapping = declare(VanDerPol, "test/PresetMapping-v0", preset=load_yaml(path.read_text()))
    default, recipes = as_mapping.recipes()
    assert (default, recipes) == as_file.recipes() and default == "default" and recipes["default"].settings["total_steps"] == 3000
    with pytest.raises(SystemSpecError, match="preset"):
        declare(VanDerPol, "test/PresetBroken-v0", preset={"recipes": {"default": {"extends": "missing"}}})


@pytest.mark.slow  # a few seconds: the whole suite runs it, the fast tier does not
def test_a_study_run_in_a_fresh_process_loads_the_user_s_system(tmp_path) -> None:
    """A Ray worker is a fresh process: the trial carries its --import and loads it there."""
    plan = textwrap.dedent(
        f"""
        import pickle, sys
        from pimbrl.systems import import_systems
        from pimbrl.training import resolve_config
        import_systems([{DUFFING!r}])
        fields = {{"method": "mfrl", "total_steps": 60, "warmup_steps": 20, "update_after": 20, "eval_every": 60,
                  "eval_episodes": 1}}
        cfg = resolve_config("example/Duffing-v0", fields)
        sys.stdout.buffer.write(pickle.dumps(({str(tmp_path / "trial")!r}, cfg, ({DUFFING!r},))))
        """
    )
    pickled = subprocess.run([sys.executable, "-c", plan], capture_output=True, timeout=120, check=True).stdout
    (tmp_path / "trial.pkl").write_bytes(pickled)
    run = textwrap.dedent(
        f"""
        import pickle
        from pimbrl.experiments.engine import execute_run
        out = execute_run(*pickle.loads(open({str(tmp_path / "trial.pkl")!r}, "rb").read()))
        print(out["ok"], out.get("error", ""))
        """
    )
    out = subprocess.run([sys.executable, "-c", run], capture_output=True, text=True, timeout=300)
    assert out.stdout.startswith("True"), out.stdout + out.stderr
    assert json.loads((tmp_path / "trial" / "config.json").read_text())["status"] == "finished"


def test_the_builtin_index_is_what_each_builtin_module_declares() -> None:
    """registry.BUILTIN lets `import pimbrl` register the built-ins without torch: it must equal their SYSTEMs."""
    import importlib

    from pimbrl.systems import BUILTIN

    for env_id, (module, aliases, steps) in BUILTIN.items():
        system = importlib.import_module(f"pimbrl.systems.{module}").SYSTEM
        assert (system.id, system.aliases, system.episode_steps) == (env_id, aliases, steps)
        assert gym.spec(env_id).entry_point == f"{system.env.__module__}:{system.env.__name__}"
