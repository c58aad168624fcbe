"""Bad input gets a clear error: corrupt checkpoints through the CLI, malformed bench options, out-of-range conditions.

What other files already cover is not repeated here: CLI flag checks of fit/simulate
(tests/test_cli.py, tests/test_cli_errors.py), load_subspace on truncated, non-JSON, missing and
other-scene checkpoints (tests/trainers/test_fit.py), env ids and model files (tests/envs,
tests/trainers/test_agents.py), non-finite actions and loads (test_stability.py, tests/envs).
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import torch

import redsim  # noqa: F401  (registers the ids)
from redsim import pretrained, scenes
from redsim.runtime import LatentStepper

Cli = Callable[..., tuple[int, str, str]]


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A copy of the shipped mini-chain checkpoint (.pt and .json)."""
    folder = tmp_path_factory.mktemp("ckpt")
    source = pretrained.path("mini_chain")
    for suffix in (".pt", ".json"):
        (folder / f"mini{suffix}").write_bytes(source.with_suffix(suffix).read_bytes())
    return folder / "mini.pt"


def _broken(checkpoint: Path, folder: Path, how: str) -> Path:
    """A broken copy of ``checkpoint`` in ``folder``: ``truncated`` .pt, ``json`` not valid, ``no_pt``."""
    stem = folder / how
    pt, meta = checkpoint.read_bytes(), checkpoint.with_suffix(".json").read_text()
    if how == "truncated":
        stem.with_suffix(".pt").write_bytes(pt[: len(pt) // 3])
        stem.with_suffix(".json").write_text(meta)
    elif how == "json":
        stem.with_suffix(".pt").write_bytes(pt)
        stem.with_suffix(".json").write_text(meta[: len(meta) // 2])
    elif how == "other_scene":  # the mini chain's weights under the chain scene's metadata
        stem.with_suffix(".pt").write_bytes(pt)
        stem.with_suffix(".json").write_text(pretrained.path("chain").with_suffix(".json").read_text())
    else:
        stem.with_suffix(".json").write_text(meta)
    return stem.with_suffix(".pt")


@pytest.mark.parametrize("command", ["inspect", "sample", "animate"])
@pytest.mark.parametrize(
    ("how", "expected"),
    [
        ("truncated", "corrupt or truncated"),
        ("json", "not valid JSON"),
        ("no_pt", "the weights file is missing"),
        ("other_scene", "in the .pt but"),
    ],
)
def test_broken_checkpoints_are_one_line_exit_2(
    cli: Cli, checkpoint: Path, tmp_path: Path, command: str, how: str, expected: str
) -> None:
    path = _broken(checkpoint, tmp_path, how)
    extra = ["--out", str(tmp_path / "out")] if command != "inspect" else []
    code, out, err = cli(command, str(path), *extra)
    assert code == 2 and out == "", err
    assert err.count("\n") == 1 and err.startswith("redsim: error: ") and expected in err
    assert "Traceback" not in err


def test_the_intact_copy_loads(cli: Cli, checkpoint: Path) -> None:
    code, out, err = cli("inspect", str(checkpoint))
    assert code == 0 and "mini_chain" in out, err


@pytest.mark.parametrize(
    ("argv", "expected"),
    [
        (["--steps", "0"], "--steps must be >= 1, got 0"),
        (["--long-steps", "-3"], "--long-steps must be >= 1, got -3"),
        (["--steps", "many"], "invalid int value"),
        (["--envs", "RedSim/Nope-v0"], "unknown env 'RedSim/Nope-v0'; valid:"),
        (["--regimes", "stiff,wobbly"], "unknown regime(s) ['wobbly']"),
        (["--regimes", ""], "--regimes"),
        (["--copies", "0"], "--copies must be >= 1, got 0"),
        (["--chain-full-steps", "0"], "--chain-full-steps must be >= 1, got 0"),  # it ran --chain-steps full steps
        (["--regimes", "mujoco", "--chain-full-steps", "-1"], "--chain-full-steps must be >= 1, got -1"),  # traceback
        (
            ["--regimes", "stiff", "--copies", "7", "--chain-steps", "5"],
            "--copies, --chain-steps not used by --regimes",
        ),
        (["--regimes", "mujoco", "--steps", "5", "--seed", "1", "--budget", "9"], "--steps, --seed, --budget not used"),
        (["--regimes", "fuzz", "--long-steps", "5"], "--long-steps not used by --regimes fuzz"),
        (["--budget", "-5"], "--budget: must be a number of seconds > 0, got '-5'"),
        (["--budget", "nan"], "--budget: must be a number of seconds > 0, got 'nan'"),
    ],
)
def test_bench_stability_options_are_checked(cli: Cli, argv: list[str], expected: str) -> None:
    code, out, err = cli("bench", "stability", *argv)
    assert code == 2 and out == "" and expected in err, err


def test_bench_stability_fails_on_a_redsim_chain_run_that_went_non_finite(
    cli: Cli, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The mujoco regime's redsim chains count towards the exit status as every other redsim run does (a NaN or an
    unreported gain there exited 0), and their cells show the non-finite steps."""
    from redsim.benches import stability

    row = {"space": "latent", "steps": 1, "free_energy_J": 1.0, "blew_up": True, "failures_detected": 0}
    label = stability.chain_scenarios()[0][0]
    monkeypatch.setattr(stability, "mujoco_chain_cases", lambda steps: None)
    for bad, code in (({"nan": 1, "unreported": 0}, 3), ({"nan": 0, "unreported": 2}, 4)):
        rows = [{"scenario": label, **row, **bad}]
        monkeypatch.setattr(stability, "redsim_chain_cases", lambda *a, rows=rows, **k: rows)
        got, out, err = cli("bench", "stability", "--regimes", "mujoco", "--chain-steps", "1")
        assert got == code and "must be 0" in err, err
        assert f"blew up (1 steps, {bad['nan']} non-finite, 0 failures detected" in out
    # a chain that blew up by its energy alone (finite, every gain reported) fails the command too: it exited 0
    rows = [{"scenario": label, **row, "nan": 0, "unreported": 0}]
    monkeypatch.setattr(stability, "redsim_chain_cases", lambda *a, **k: rows)
    got, _, err = cli("bench", "stability", "--regimes", "mujoco", "--chain-steps", "1")
    assert got == 4 and f"redsim's chain blew up in {label} (latent)" in err, err


def test_condition_outside_its_range_is_flagged_by_the_stepper_and_refused_by_set_state() -> None:
    scene = scenes.build("conditional_bar")
    stepper = LatentStepper(scene, pretrained.load("conditional_bar", scene), 0.02)
    space = scene.condition_space
    inside = space.default.reshape(1, -1).float()
    outside = (space.high + 0.2 * (space.high - space.low)).reshape(1, -1).float()
    z = stepper.rest_latent(inside)
    for cond, flagged in ((inside, False), (outside, True)):
        z_next, stats = stepper.step(z, z, None, cond)
        assert bool(stats.out_of_range[0]) is flagged and bool(torch.isfinite(z_next).all())
    with pytest.raises(ValueError, match="cond must be finite"):
        stepper.step(z, z, None, torch.full_like(inside, float("nan")))
    env = gym.make("RedSim/ConditionalBar-v0").unwrapped
    env.reset(seed=0)
    state = env.get_state()
    env.set_state(state)
    low, high = space.low.numpy(), space.high.numpy()
    for bad in (high + 0.2 * (high - low), low - 0.1 * (high - low)):
        with pytest.raises(ValueError, match=r"state\['cond'\] must lie in the condition space"):
            env.set_state({**state, "cond": bad.astype(np.float32)})


def test_a_state_too_far_out_for_the_map_is_refused_and_the_env_keeps_its_own() -> None:
    """z = 1e30 decodes to finite float32 positions (2e28 m) whose distance overflows: the next step's reward was
    -inf (the step flagged diverged, but the return poisoned). A far but usable z (1e3) still steps, flagged."""
    env = gym.make("RedSim/MiniChain-v0").unwrapped
    env.reset(seed=0)
    state = env.get_state()
    far = {**state, "z": np.full_like(state["z"], 1e30), "z_prev": np.full_like(state["z_prev"], 1e30)}
    with pytest.raises(ValueError, match=r"state\['z'\] of copies \[0\] is too far out for the map"):
        env.set_state(far)
    np.testing.assert_array_equal(env.get_state()["z"], state["z"])  # nothing changed
    env.set_state({**state, "z": np.full_like(state["z"], 1e3), "z_prev": np.full_like(state["z_prev"], 1e3)})
    _, reward, terminated, _, info = env.step(np.zeros(3, np.float32))
    assert np.isfinite(reward) and terminated and info["diverged"]
    # the sharded env refuses it before its workers (a worker's refusal closes the env), naming the env's copies
    venv = gym.make_vec("RedSim/MiniChain-v0", num_envs=2, vectorization_mode="vector_entry_point", shards=2)
    try:
        venv.reset(seed=0)
        state = venv.get_state()
        far = {**state, "z": state["z"].copy()}
        far["z"][1] = 1e30
        with pytest.raises(ValueError, match=r"state\['z'\] of copies \[1\] is too far out for the map"):
            venv.set_state(far)
        venv.step(np.zeros((2, 3), np.float32))  # still open
    finally:
        venv.close()


@pytest.mark.parametrize(("row", "code"), [({"nan": 2}, 3), ({"unreported": 1}, 4), ({"energy_gains": 5}, 0)])
def test_bench_stability_fails_when_a_must_be_zero_count_is_not(
    cli: Cli, monkeypatch: pytest.MonkeyPatch, row: dict, code: int
) -> None:
    """A CI job running the bench must see a NaN or an unreported energy gain in its exit status."""
    from redsim.benches import stability

    monkeypatch.setitem(stability.REGIMES, "canned", lambda steps, budget, rows: rows.append({"steps": 10, **row}))
    monkeypatch.setattr(stability, "report", lambda result: [])
    got, _, err = cli("bench", "stability", "--regimes", "canned")
    assert got == code, err
    assert ("must be 0" in err) == (code != 0)


def test_a_load_too_large_for_the_dtype_is_never_converged() -> None:
    """A finite load whose norm overflows makes every threshold inf; the step is flagged, not "converged"."""
    from redsim.integrators import FullSpace, FullState, ImplicitEuler
    from redsim.solvers import ConvergenceError

    scene = scenes.build("mini_chain")
    stepper = LatentStepper(scene, pretrained.load("mini_chain", scene), 0.02)
    z = stepper.rest_latent()
    for force in (1e20, 1e30):  # float32: the norm of the load overflows
        _, stats = stepper.step(z, z, torch.tensor([[[force, 0.0, 0.0]]], dtype=torch.float64))
        assert not bool(stats.converged) and bool(stats.diverged), force
        # not the 0 or NaN of a division by the inf scale (a review's finding)
        assert float(stats.residual) == float(stats.energy_gain_tolerance) == math.inf, force
    with pytest.raises(ValueError, match="loads must be finite"):  # inf once cast to float32
        stepper.step(z, z, torch.tensor([[[1e100, 0.0, 0.0]]], dtype=torch.float64))
    q0 = scene.q_seed.double()
    full = ImplicitEuler(FullSpace(scene), 0.02, strict=True)
    with pytest.raises(ConvergenceError, match="not finite"):
        full.step(FullState(q0.clone(), q0.clone(), 0.0), torch.tensor([[1e200, 0.0, 0.0]], dtype=torch.float64))


def test_a_tiny_time_step_at_rest_raises_no_energy_gain_flag() -> None:
    """At h = 1e-6 the float32 round-off of q, divided by h^2 in K, is the size of any energy change: the flag's
    tolerance counts it, so a scene at rest is not flagged (it was on every step)."""
    scene = scenes.build("mini_chain")
    stepper = LatentStepper(scene, pretrained.load("mini_chain", scene), 1e-6)
    z = z_prev = stepper.rest_latent()
    for _ in range(10):
        z_next, stats = stepper.step(z, z_prev)
        assert not bool(stats.energy_gain.any())
        z_prev, z = z, z_next


@pytest.mark.parametrize(
    ("kwargs", "expected"),
    [
        ({"dt": 1e-300}, r"dt must be a finite number of seconds >= 1e-06"),  # h^2 underflowed to 0
        ({"dt": 1e-20}, r"dt must be a finite number of seconds >= 1e-06"),  # 1/h^2 overflowed float32
        ({"dt": True}, "dt must be a number of seconds"),
        ({"dt": None}, "dt must be a number of seconds"),
        ({"frame_skip": True}, "frame_skip must be an integer"),
        ({"frame_skip": 0}, r"frame_skip must be an integer in \[1, 1000\] \(MAX_FRAME_SKIP"),
        ({"frame_skip": 10**12}, r"frame_skip must be an integer in \[1, 1000\] \(MAX_FRAME_SKIP"),
        ({"include_q": "yes"}, "include_q must be True or False"),
        ({"stepper_options": {"bogus": 1}}, r"unknown stepper_options \['bogus'\]; valid: \['compile'"),
        ({"scene_params": "x"}, "scene_params must be a dict"),
        ({"target_spread": 1e30}, "target_spread 1e.30 puts targets inf m from rest"),
        ({"device": "garbage"}, r"device must be 'cpu' or 'cuda\[:N\]'"),
        ({"device": "meta"}, r"device must be 'cpu' or 'cuda\[:N\]'"),
        ({"dtype": "float16"}, r"dtype must be one of \['float32', 'float64'\]"),
    ],
)
def test_env_arguments_of_the_wrong_kind_are_refused_at_make(kwargs: dict, expected: str) -> None:
    with pytest.raises(ValueError, match=expected):
        gym.make("RedSim/MiniChain-v0", **kwargs)


def test_the_full_space_integrator_refuses_a_time_step_too_small_for_its_arithmetic() -> None:
    from redsim.integrators import FullSpace, ImplicitEuler

    with pytest.raises(ValueError, match=r"dt must be a finite number of seconds >= 1e-06"):
        ImplicitEuler(FullSpace(scenes.build("mini_chain")), 1e-200)


@pytest.mark.parametrize(
    ("kwargs", "expected"),
    [
        ({"max_iter": float("inf")}, "max_iter must be an integer >= 1, got inf"),  # was OverflowError
        ({"max_iter": float("nan")}, "max_iter must be an integer >= 1, got nan"),
        ({"max_iter": True}, "max_iter must be an integer >= 1, got True"),
        ({"tol": "1e-8"}, "tol must be finite and > 0, got '1e-8'"),  # was TypeError
    ],
)
def test_solver_settings_of_the_wrong_kind_are_a_value_error(kwargs: dict, expected: str) -> None:
    """ImplicitEuler, static_equilibrium's solver and LatentStepper share one check of tol and max_iter."""
    from redsim.integrators import FullSpace, ImplicitEuler
    from redsim.solvers import check_settings

    scene = scenes.build("mini_chain")
    with pytest.raises(ValueError, match=re.escape(expected)):
        ImplicitEuler(FullSpace(scene), 0.01, **kwargs)
    with pytest.raises(ValueError, match=re.escape(expected)):
        LatentStepper(scene, pretrained.load("mini_chain", scene), 0.02, **kwargs)
    with pytest.raises(ValueError, match=re.escape(expected)):
        check_settings(kwargs.get("tol", 1e-8), kwargs.get("max_iter", 50))


def test_a_latent_space_refuses_a_non_finite_condition_and_a_latent_its_map_overflows_at_is_unconverged() -> None:
    """LatentSpace took a NaN condition and its step then died in NumPy's SVD (LinAlgError), as did a latent that
    overflows the float32 map (|z| >= 3.4e38): the condition is refused, the step reports that it did not converge."""
    from redsim.integrators import ImplicitEuler, LatentSpace

    bar = scenes.build("conditional_bar")
    with pytest.raises(ValueError, match=r"the condition must be finite, got \[nan, 0\.5\]"):
        LatentSpace(bar, pretrained.load("conditional_bar", bar), cond=torch.tensor([float("nan"), 0.5]))
    chain = scenes.build("mini_chain")
    integrator = ImplicitEuler(LatentSpace(chain, pretrained.load("mini_chain", chain)), 0.02)
    _, info = integrator.step(integrator.initial_state(torch.full((4,), 1e39, dtype=torch.float64)))
    assert not info.converged


@pytest.mark.parametrize("value", [None, 5, [0.3, 0.6, 0.9], "ab"])
def test_a_range_parameter_that_is_not_a_pair_is_a_value_error(value: object) -> None:
    with pytest.raises(ValueError, match=r"pin_location_range must be a pair \(low, high\)"):
        scenes.build("conditional_bar", pin_location_range=value)


@pytest.mark.skipif(torch.cuda.is_available(), reason="checks the message where CUDA is missing")
def test_a_cuda_device_without_cuda_is_a_clear_error() -> None:
    with pytest.raises(ValueError, match=r"device 'cuda' is not available: torch.cuda.is_available\(\) is False"):
        gym.make("RedSim/MiniChain-v0", device="cuda")


def test_torch_and_numpy_dtypes_name_the_same_env_dtype() -> None:
    for dtype in ("float64", torch.float64, np.float64):
        assert gym.make("RedSim/MiniChain-v0", dtype=dtype).unwrapped.sim.torch_dtype == torch.float64


def test_an_interrupt_inside_a_step_leaves_the_env_as_it_was(monkeypatch: pytest.MonkeyPatch) -> None:
    """The step is atomic: Ctrl-C (or a task's error) mid-step neither advances the state nor stales x."""
    env = gym.make("RedSim/Klann-v0")
    env.reset(seed=0)
    for _ in range(3):
        env.step(np.ones(1, np.float32))
    sim = env.unwrapped.sim
    state, obs = env.unwrapped.get_state(), sim.observe()

    def interrupt(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(sim, "full_positions", interrupt)
    with pytest.raises(KeyboardInterrupt):
        env.step(np.ones(1, np.float32))
    monkeypatch.undo()
    np.testing.assert_array_equal(sim.observe(), obs)
    for key in ("z", "z_prev", "params", "model"):
        np.testing.assert_equal(env.unwrapped.get_state()[key], state[key])
    env.step(np.ones(1, np.float32))


@pytest.mark.parametrize("env_id", ["RedSim/MiniChain-v0", "RedSim/Klann-v0", "RedSim/ConditionalBar-v1"])
def test_making_an_env_leaves_torch_s_global_random_stream_alone(env_id: str) -> None:
    torch.manual_seed(0)
    expected = torch.rand(3)
    torch.manual_seed(0)
    gym.make(env_id)
    gym.make_vec(env_id, 2, "vector_entry_point")
    assert torch.equal(torch.rand(3), expected)


def test_set_state_names_a_malformed_setting_or_model() -> None:
    """A ``setting`` that is not a dict was a bare ``TypeError: 'int' object is not iterable``, a ``model`` of strings
    torch's conversion error and a ragged one NumPy's: each is now a ValueError naming the key; a NaN model still
    means "none built yet" and steps as a fresh one."""
    env = gym.make("RedSim/MiniChain-v0").unwrapped
    env.reset(seed=0)
    state = env.get_state()
    with pytest.raises(ValueError, match=r"state\['setting'\] must be the dict get_state\(\) wrote, got 5"):
        env.set_state({**state, "setting": 5})
    for model in (np.full((4, 4), "x"), [[1.0], [1.0, 2.0]]):
        with pytest.raises(ValueError, match=r"state\['model'\] must be a numeric array of shape \[1, 4, 4\]"):
            env.set_state({**state, "model": model})
    env.set_state({**state, "model": np.full((4, 4), np.nan)})
    fresh = env.step(np.zeros(3, np.float32))[0]
    env.set_state({**state, "model": None})
    np.testing.assert_array_equal(env.step(np.zeros(3, np.float32))[0], fresh)
    # a ``params`` that is not a dict: the native vector env raised TypeError, the sharded one IndexError
    with pytest.raises(ValueError, match=r"state\['params'\] must be the task parameters' dict get_state\(\) wrote"):
        env.set_state({**state, "params": 5})
    for shards in (1, 2):
        venv = gym.make_vec("RedSim/MiniChain-v0", num_envs=3, vectorization_mode="vector_entry_point", shards=shards)
        try:
            venv.reset(seed=0)
            batch = venv.get_state()
            with pytest.raises(ValueError, match=r"state\['params'\] must (be the task|hold one entry per copy)"):
                venv.set_state({**batch, "params": 5})
            venv.step(np.zeros((3, 3), np.float32))  # still open and usable
        finally:
            venv.close()


def test_the_reference_names_inputs_that_are_not_numbers() -> None:
    """As the runtime: a string or ragged load, a string state or condition was torch's TypeError "new(): invalid
    data type 'str'" (or NumPy's ragged error) naming nothing; now a ValueError names the argument and its shape."""
    from redsim.integrators import FullSpace, FullState, ImplicitEuler

    chain = scenes.build("mini_chain").to(dtype=torch.float64)
    integrator = ImplicitEuler(FullSpace(chain), 0.02)
    state = integrator.initial_state()
    for loads in ("abc", [[1.0], [1.0, 2.0]]):
        with pytest.raises(ValueError, match=r"loads must be an array of numbers of shape \[1, 1, 3\] or \[1, 3\]"):
            integrator.step(state, loads)
    with pytest.raises(ValueError, match=r"load on handle 'bottom' must be an array of numbers of shape \[3\]"):
        integrator.step(state, {"bottom": "ab"})
    with pytest.raises(ValueError, match=r"state.q must be an array of numbers of shape \[24\]"):
        integrator.step(FullState("abc", state.q_prev, 0.0))  # type: ignore[arg-type]
    with pytest.raises(ValueError, match=r"loads must be an array of real numbers .* got complex128"):
        chain.energy(state.q[None], np.array([[1j, 0.0, 0.0]]))
    bar = scenes.build("conditional_bar")
    with pytest.raises(ValueError, match=r"condition must be an array of numbers of shape \[1, 2\]"):
        bar.energy(bar.q_seed[None], None, "ab")
    assert bool(torch.isfinite(integrator.step(state, [[0.0, 0.0, 1.0]])[0].q).all())  # lists still work
