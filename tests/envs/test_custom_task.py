"""A user's own Task through redsim.envs.make: what it returns is checked, and its parameters keep their dtypes."""

from __future__ import annotations

import pickle

import numpy as np
import pytest
import torch
from gymnasium.utils.env_checker import check_env

import redsim
from redsim.envs.base import Task


class HoldHeight(Task):
    """Hold the mini chain's lower link at a height drawn per episode; counts its steps in an int parameter."""

    name = "hold_height"
    action_size = 3
    reward_terms = ("height", "control")

    def bind(self, sim) -> None:
        self.handle = sim.scene.handle("bottom")
        self.shape = (len(sim.scene.handles), sim.scene.dim)

    def extras_bounds(self):
        return np.full(2, -10.0), np.full(2, 10.0)

    def observation_structure(self):
        return {"height": 1, "height_error": 1}

    def sample(self, rng, sim, z_rest, cond):
        target = torch.tensor(rng.uniform(-0.2, 0.0), dtype=sim.torch_dtype)
        return {"target": target, "clock": torch.tensor(0), "pushed": torch.tensor(False)}

    def loads(self, action, params):
        params["clock"] += 1
        params["pushed"] |= params["clock"] >= 2
        loads = torch.zeros(action.shape[0], *self.shape, dtype=action.dtype)
        loads[:, 0] = 5.0 * action
        return loads

    def _height(self, x):
        return self.handle.position(x)[:, 1]

    def extras(self, x, x_prev, params):
        height = self._height(x)
        return torch.stack([height, params["target"] - height], 1)

    def reward(self, x, action, params):
        terms = {"height": -(self._height(x) - params["target"]).abs(), "control": -0.05 * action.pow(2).mean(1)}
        return terms["height"] + terms["control"], terms


def _env(task: Task):
    return redsim.envs.make("mini_chain", task=task, max_episode_steps=20)


def test_a_custom_task_passes_the_checkers_and_keeps_its_parameter_dtypes() -> None:
    env = _env(HoldHeight())
    check_env(env.unwrapped, skip_render_check=True)
    env.reset(seed=0)
    for _ in range(3):
        env.step(env.action_space.sample())
    state = env.unwrapped.get_state()
    assert state["params"]["clock"].dtype == np.int64 and state["params"]["pushed"].dtype == np.bool_
    env.unwrapped.set_state(state)
    again = pickle.loads(pickle.dumps(env))
    for restored in (env, again):
        params = restored.unwrapped.sim.params
        assert params["clock"].dtype == torch.int64 and params["pushed"].dtype == torch.bool
        restored.step(np.zeros(3, np.float32))  # `|=` on a bool parameter works after the restore
        assert int(restored.unwrapped.sim.params["clock"][0]) == 4


class FirstRewardOnly(HoldHeight):
    def reward(self, x, action, params):
        reward, terms = super().reward(x, action, params)
        return reward[:1], terms


class ColumnTerminated(HoldHeight):
    def terminated(self, x, params):
        return torch.zeros(x.shape[0], 1, dtype=torch.bool)


class NanReward(HoldHeight):
    def reward(self, x, action, params):
        reward, terms = super().reward(x, action, params)
        return reward * float("nan"), {k: v * float("nan") for k, v in terms.items()}


class OtherTerms(HoldHeight):
    def reward(self, x, action, params):
        reward, terms = super().reward(x, action, params)
        return reward + 5.0, {"foo": terms["height"], "control": terms["control"]}


@pytest.mark.parametrize(
    ("task", "expected"),
    [
        (FirstRewardOnly(), r"Task reward must be a torch tensor of shape \[B\] = \[4\], got \[1\]"),
        (ColumnTerminated(), r"Task terminated must be a torch tensor of shape \[B\]"),
        (NanReward(), "not finite"),
        (OtherTerms(), "are not reward_terms"),
    ],
)
def test_what_a_task_returns_is_checked_at_every_step(task: Task, expected: str) -> None:
    from redsim.envs.vector import LatentVectorEnv

    venv = LatentVectorEnv(_env(task).unwrapped, 4)
    venv.reset(seed=0)
    with pytest.raises(ValueError, match=expected):
        venv.step(np.zeros((4, 3), np.float32))


class WideExtras(HoldHeight):
    def extras(self, x, x_prev, params):
        return torch.cat([super().extras(x, x_prev, params), x[:, :1]], 1)


class NumpyExtras(HoldHeight):
    def extras(self, x, x_prev, params):
        return super().extras(x, x_prev, params).numpy()


class NanAfterAStep(HoldHeight):
    observed = 0

    def extras(self, x, x_prev, params):
        self.observed += 1  # the reset's observation is finite, the step's is not
        return super().extras(x, x_prev, params) * (1.0 if self.observed == 1 else float("nan"))


@pytest.mark.parametrize(
    ("task", "expected"),
    [
        (WideExtras(), r"Task extras must be a torch tensor of shape \[B, k\] = \[1, 2\], got \[1, 3\]"),
        (NumpyExtras(), r"Task extras must be a torch tensor of shape \[B, k\] = \[1, 2\], got ndarray"),
        (NanAfterAStep(), r"Task extras is not finite"),
    ],
)
def test_what_a_task_s_extras_return_is_checked_at_every_observation(task: Task, expected: str) -> None:
    env = _env(task)
    with pytest.raises(ValueError, match=expected):
        env.reset(seed=0)
        before = env.unwrapped.get_state()
        env.step(np.zeros(3, np.float32))
    if isinstance(task, NanAfterAStep):  # refused at the step's observation: the step is undone
        assert np.array_equal(env.unwrapped.get_state()["z"], before["z"])


def test_extras_need_only_be_finite_where_x_is() -> None:
    """A copy whose x is not finite (a diverged state) may report non-finite extras; a finite one may not."""
    env = _env(HoldHeight())
    env.reset(seed=0)
    sim = env.unwrapped.sim
    finite_x = sim.x
    sim.x = torch.full_like(finite_x, float("nan"))  # the extras (the link's height) follow: NaN
    assert sim.observe().shape == (1, 2 * sim.latent_dim + 2)
    sim.x = finite_x
    sim.task.extras = lambda x, x_prev, params: torch.full((1, 2), float("nan"), dtype=x.dtype)
    with pytest.raises(ValueError, match="Task extras is not finite"):
        sim.observe()


class Unbounded(HoldHeight):
    def extras_bounds(self):
        return np.full(2, -np.inf), np.full(2, np.inf)


class WrongBlocks(HoldHeight):
    def observation_structure(self):
        return {"height": 1, "height_error": 1, "ghost": 5}


def test_a_task_s_observation_contract_is_checked_when_the_env_is_made() -> None:
    with pytest.raises(ValueError, match="extras_bounds must be finite"):
        _env(Unbounded())
    with pytest.raises(ValueError, match="does not add up"):
        _env(WrongBlocks())


def test_a_method_a_task_leaves_out_is_named() -> None:
    """A Task subclass without a required method raised a bare NotImplementedError (an empty message)."""

    class Bare(Task):
        action_size = 1

    with pytest.raises(NotImplementedError, match=r"Bare\.extras_bounds is not implemented: a Task implements"):
        _env(Bare())


class FloatTarget(HoldHeight):
    def sample(self, rng, sim, z_rest, cond):
        return {**super().sample(rng, sim, z_rest, cond), "target": 0.1}


class ChangingKeys(HoldHeight):
    def sample(self, rng, sim, z_rest, cond):
        drawn = super().sample(rng, sim, z_rest, cond)
        return drawn if rng.random() < 0.5 else {**drawn, "extra": torch.tensor(1.0)}


def test_what_a_task_samples_is_checked_at_reset() -> None:
    with pytest.raises(ValueError, match="must return torch tensors, got float for 'target'"):
        _env(FloatTarget()).reset(seed=0)
    env = _env(ChangingKeys())
    with pytest.raises(ValueError, match="another episode"):
        for seed in range(20):
            env.reset(seed=seed)


def test_the_reach_task_s_default_force_finds_gravity_by_type_not_by_name() -> None:
    """A user's effect named "gravity" is not the scene's weight: no gravity effect, the default 1 N."""
    from redsim import scenes
    from redsim.effects import Effect
    from redsim.envs.factory import DEFAULT_FORCE_FRACTION, default_force
    from redsim.scene import SceneBuilder

    class Tether(Effect):
        kind = "tether"

        def __init__(self, name, dofs) -> None:
            self.name, self.element_dofs = name, dofs

        def element_energy(self, xe, cond=None, loads=None):
            return 0.5 * (xe**2).sum(-1)

    b = SceneBuilder(dim=2)
    ids = b.add_particles(torch.tensor([[0.0, -0.5], [0.3, -0.4]], dtype=torch.float64), torch.ones(2))
    b.add_effect(Tether("gravity", b.particle_dofs(ids)))
    assert default_force(b.finalize("tethered")) == 1.0
    chain = scenes.build("mini_chain")
    gravity = next(e for e in chain.effects if e.kind == "gravity")
    weight = float(gravity.masses.sum()) * float(gravity.acceleration.norm())
    assert default_force(chain) == pytest.approx(DEFAULT_FORCE_FRACTION * weight)


def test_the_first_reset_leaves_the_task_parameters_as_drawn() -> None:
    """The first reset probes the action scale through Task.loads, which may advance per-episode parameters (a
    clock): it works on a copy, so a seed draws the same episode at the first reset as later (a review: clock 3)."""
    env = _env(HoldHeight())
    env.reset(seed=0)
    first = {k: v.clone() for k, v in env.unwrapped.sim.params.items()}
    env.reset(seed=0)
    again = env.unwrapped.sim.params
    assert all(torch.equal(first[k], again[k]) for k in again) and int(first["clock"][0]) == 0


class NumpyLoads(HoldHeight):
    def loads(self, action, params):
        return super().loads(action, params).numpy()


class ShortStart(HoldHeight):
    def start(self, sim, row, z_rest):
        return z_rest[:1]


class FlatFramePoints(HoldHeight):
    def frame_points(self, sim):
        return np.zeros((3, 2))


class RaggedBounds(HoldHeight):
    def extras_bounds(self):
        return np.full(2, -10.0), np.full(3, 10.0)


@pytest.mark.parametrize(
    ("task", "call", "expected"),
    [
        (
            NumpyLoads(),
            "reset",
            r"Task.loads must return a torch tensor of shape \[B, H, D\] = \[1, 1, 3\], got ndarray",
        ),
        (ShortStart(), "reset", r"Task.start must return a torch tensor of shape \[d\] = \[4\], got \[1\]"),
        (FlatFramePoints(), "render", r"Task.frame_points must return finite points \[P, D\] = \[P, 3\]"),
        (RaggedBounds(), "make", r"Task.extras_bounds must return \(low, high\), two 1-D arrays of one length"),
    ],
)
def test_a_hook_returning_the_wrong_shape_is_named(task: Task, call: str, expected: str) -> None:
    """These were broadcast or reshaped silently (a short start, flat frame points) or failed deep inside (numpy
    loads, ragged bounds): a review's findings."""
    with pytest.raises(ValueError, match=expected):
        env = redsim.envs.make("mini_chain", task=task, max_episode_steps=20, render_mode="rgb_array")
        env.reset(seed=0)
        if call == "render":
            env.render()
