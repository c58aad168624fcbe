"""Goal-conditioned observations for the reach envs, in Gymnasium-Robotics' dict convention (SB3's HER).

:class:`GoalObservation` wraps an env whose task is :class:`redsim.envs.reach.HandleReach` (MiniChain, Chain,
ClothBall, HangingCloth, ConditionalBar, or a :func:`redsim.envs.make` env with ``task="reach"``) so that
its observation is a dict

- ``"observation"``: the flat observation without its goal-dependent block (``target_offset``),
- ``"achieved_goal"``: the goal handle's position along the goal axes [m], shape [k],
- ``"desired_goal"``: the target [m], shape [k],

and ``compute_reward(achieved_goal, desired_goal, info)`` gives the reward for any goal, batched over leading
axes, which is what hindsight experience replay (HER) relabels with::

    from stable_baselines3 import SAC, HerReplayBuffer
    env = GoalObservation(gym.make("RedSim/MiniChain-v0", max_episode_steps=50))
    SAC("MultiInputPolicy", env, replay_buffer_class=HerReplayBuffer).learn(10_000)

The reward depends on the goals alone, -d / L + bonus [d < r] (:class:`HandleReach`'s distance and success terms),
as HER needs: SB3's ``HerReplayBuffer`` relabels with empty ``info`` dicts unless asked to copy them. So the wrapper
leaves out the task's control cost (still reported in ``info["reward_control"]``) and returns this reward from
``step`` too. ``GoalObservation(env, control_cost=True)`` keeps it: the reward is then the env's own, and
``compute_reward`` reads the control term from the ``info`` of each transition (SB3:
``replay_buffer_kwargs={"copy_info_dict": True}``).

:class:`GoalVectorObservation` does the same for the native vector env, in both autoreset modes, so HER trains
on one batched simulation of all copies (stable-baselines3 through :class:`redsim.envs.sb3.SB3VecEnv`, whose
``env_method("compute_reward", ...)`` it answers)::

    venv = SB3VecEnv.make("RedSim/MiniChain-v0", num_envs=8, goal=True, max_episode_steps=50)
    SAC("MultiInputPolicy", venv, replay_buffer_class=HerReplayBuffer, learning_starts=8 * 51).learn(10_000)

(HER samples only once every copy has ended an episode: ``learning_starts`` counts the transitions of all copies.)
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces
from gymnasium.vector import VectorEnv, VectorObservationWrapper, VectorWrapper
from gymnasium.vector.utils import batch_space
from gymnasium.wrappers.vector import DictInfoToList

from redsim.envs.reach import HandleReach
from redsim.envs.vector import LatentVectorEnv

GOAL_BLOCK = "target_offset"
"""The observation block that depends on the desired goal: left out of ``"observation"``."""

REACH_ENVS = "MiniChain, Chain, ClothBall, HangingCloth, ConditionalBar"


def _reach_task(task: Any, owner: str, wrapper: str) -> HandleReach:
    """``task``, checked to be a reach task (``owner``: the env's class name, for the error).

    Raises:
        TypeError: another task (its observation has no goal to relabel).
    """
    if not isinstance(task, HandleReach):
        raise TypeError(
            f"{wrapper} needs a reach env (task HandleReach), got task {type(task).__name__} of {owner}; "
            f"reach envs: {REACH_ENVS}"
        )
    return task


def _check_own_observation(env: Any, layers: type, changing: tuple[type, ...], own: bool, wrapper: str) -> None:
    """Check that ``env`` gives its base env's own observation and info: no wrapper among its ``layers`` is one of
    ``changing``, and ``own`` (its observation space is the base env's).

    Raises:
        TypeError: a wrapper inside ``wrapper`` that changes the observation (the goals would be in other units)
            or, for a vector env, the info's layout (``final_obs`` is read from it).
    """
    inner = env
    while isinstance(inner, layers):
        if isinstance(inner, changing):
            raise TypeError(
                f"{wrapper} must wrap the env's own observation and info, but {type(inner).__name__} changes "
                f"them; put it outside {wrapper}"
            )
        inner = inner.env
    if not own:
        raise TypeError(f"{wrapper} needs the env's own flat Box observation")


class GoalSplit:
    """Where a reach env's flat observation holds the goals: its dict observation and dict observation space.

    Args:
        structure: The env's observation blocks (name -> size, in order; ``observation_structure``).
    """

    def __init__(self, structure: Mapping[str, int]) -> None:
        blocks, start = {}, 0
        for name, size in structure.items():
            blocks[name] = slice(start, start + size)
            start += size
        if "handle_position" not in blocks or GOAL_BLOCK not in blocks:
            raise TypeError(f"not a reach env's observation (blocks {', '.join(blocks)}): no goal to split off")
        self.achieved = blocks["handle_position"]
        self.offset = blocks[GOAL_BLOCK]
        self.keep = np.concatenate([np.arange(s.start, s.stop) for n, s in blocks.items() if n != GOAL_BLOCK])

    def space(self, flat: spaces.Box) -> spaces.Dict:
        """The dict observation space of the flat observation space ``flat`` (one copy)."""
        goal = spaces.Box(flat.low[self.achieved], flat.high[self.achieved], dtype=np.float32)
        return spaces.Dict(
            {
                "observation": spaces.Box(flat.low[self.keep], flat.high[self.keep], dtype=np.float32),
                "achieved_goal": goal,
                "desired_goal": goal,
            }
        )

    def __call__(self, flat: np.ndarray, desired: np.ndarray | None = None) -> dict[str, np.ndarray]:
        """The dict observation of flat observations [..., obs] whose targets are ``desired`` [..., k] [m] (None:
        read from the flat observation, the goal handle's position plus its target offset, to float32 round-off;
        how a goal-conditioned agent acts on the flat env, :class:`redsim.trainers.agents.Agent`)."""
        if desired is None:
            desired = flat[..., self.achieved] + flat[..., self.offset]
        return {
            "observation": flat[..., self.keep],
            "achieved_goal": flat[..., self.achieved],
            "desired_goal": np.array(desired, dtype=np.float32),  # a copy: never a view of the simulation
        }


class _GoalReward:
    """``compute_reward`` / ``compute_terminated`` / ``compute_truncated`` of a reach task (module doc)."""

    control_cost: bool

    @property
    def task(self) -> HandleReach:
        """The env's reach task (its distance scale, success radius and bonus set the reward)."""
        raise NotImplementedError

    def compute_reward(
        self, achieved_goal: np.ndarray, desired_goal: np.ndarray, info: Mapping[str, Any] | Sequence[Mapping[str, Any]]
    ) -> np.ndarray:
        """The reward for goals [..., k] (float32, shape [...]); ``info``: one step's info dict, or one per goal (a
        sequence or object array of shape [...], as SB3's HER passes them); read only with ``control_cost``.

        Raises:
            ValueError: goals of other shapes, or whose last axis is not the task's k (numpy broadcast them into
                rewards of other transitions).
            KeyError: ``control_cost`` and an ``info`` without ``"reward_control"`` (SB3's HER copies none unless
                ``copy_info_dict=True``).
        """
        achieved = np.asarray(achieved_goal, dtype=np.float64)
        desired = np.asarray(desired_goal, dtype=np.float64)
        k = len(self.task.goal_axes)
        if achieved.shape != desired.shape or achieved.ndim < 1 or achieved.shape[-1] != k:
            raise ValueError(
                f"achieved_goal and desired_goal must share a shape [..., {k}] (k = {k}: the goal axes), got "
                f"{list(achieved.shape)} and {list(desired.shape)}"
            )
        distance = np.linalg.norm(achieved - desired, axis=-1)
        task = self.task
        reward = -distance / task.distance_scale + task.success_bonus * (distance < task.success_radius)
        if self.control_cost:
            reward = reward + self._control(info, distance.shape)
        return reward.astype(np.float32)

    @staticmethod
    def _control(info: Mapping[str, Any] | Sequence[Mapping[str, Any]], shape: tuple[int, ...]) -> np.ndarray:
        """The control term of each transition, from its info (shape ``shape``)."""
        items = [info] if isinstance(info, Mapping) else list(np.asarray(info, dtype=object).ravel())
        missing = [i for i, item in enumerate(items) if "reward_control" not in item]
        if missing:
            raise KeyError(
                "control_cost=True needs each transition's info['reward_control'] (with SB3's HerReplayBuffer: "
                "replay_buffer_kwargs={'copy_info_dict': True})"
            )
        values = np.array([item["reward_control"] for item in items], dtype=np.float64)
        return np.broadcast_to(values[0], shape) if isinstance(info, Mapping) else values.reshape(shape)

    def compute_terminated(
        self, achieved_goal: np.ndarray, desired_goal: np.ndarray, info: Mapping[str, Any] | Sequence[Any]
    ) -> np.ndarray:
        """False for every goal [...]: a reach episode ends only by truncation or divergence, whatever the goal."""
        return np.zeros(np.shape(achieved_goal)[:-1], dtype=bool)

    def compute_truncated(
        self, achieved_goal: np.ndarray, desired_goal: np.ndarray, info: Mapping[str, Any] | Sequence[Any]
    ) -> np.ndarray:
        """False for every goal [...]: truncation is the time limit's, not the goal's."""
        return np.zeros(np.shape(achieved_goal)[:-1], dtype=bool)


class GoalObservation(_GoalReward, gym.ObservationWrapper, gym.utils.RecordConstructorArgs):
    """Dict observations {observation, achieved_goal, desired_goal} and a batched ``compute_reward`` (module doc).

    Args:
        env: A redsim env (wrapped or not) whose task is a :class:`HandleReach`.
        control_cost: Keep the task's control cost in the reward (then ``compute_reward`` needs each transition's
            ``info``); default: the reward depends on the goals alone.

    Raises:
        TypeError: the env's task is not a reach task (its observation has no goal to relabel), or a wrapper
            inside this one changes the observation (put observation wrappers outside GoalObservation).
    """

    def __init__(self, env: gym.Env, control_cost: bool = False) -> None:
        gym.utils.RecordConstructorArgs.__init__(self, control_cost=control_cost)  # env.spec remakes the wrapped env
        gym.ObservationWrapper.__init__(self, env)
        self.control_cost = bool(control_cost)
        base = env.unwrapped
        _reach_task(getattr(base, "task", None), type(base).__name__, "GoalObservation")
        changing = (gym.ObservationWrapper, gym.wrappers.NormalizeObservation)
        own = env.observation_space == base.observation_space
        _check_own_observation(env, gym.Wrapper, changing, own, "GoalObservation")
        self._split = GoalSplit(base.observation_structure)
        self.observation_space = self._split.space(base.observation_space)

    @property
    def task(self) -> HandleReach:
        """The env's reach task (its distance scale, success radius and bonus set the reward)."""
        return self.env.unwrapped.task

    def step(self, action: Any) -> tuple[dict[str, np.ndarray], float, bool, bool, dict[str, Any]]:
        obs, _, terminated, truncated, info = super().step(action)
        reward = float(self.compute_reward(obs["achieved_goal"], obs["desired_goal"], info))
        return obs, reward, terminated, truncated, info

    def observation(self, observation: np.ndarray) -> dict[str, np.ndarray]:
        return self._split(observation, self.env.unwrapped.sim.params["target"][0].detach().cpu().numpy())


class GoalVectorObservation(_GoalReward, VectorWrapper):
    """:class:`GoalObservation` for the native vector env: dict observations [N, ...] and ``compute_reward``.

    Each copy's observation, reward and ``info`` are those of a :class:`GoalObservation` over that copy, in
    either autoreset mode: with ``AutoresetMode.SAME_STEP`` the entries of ``info["final_obs"]`` are dicts with
    the ended episode's goal, and an ended copy's reward is its last step's; with ``NEXT_STEP`` a copy's reset
    step earns 0.

    Args:
        env: A :class:`redsim.envs.vector.LatentVectorEnv` of a reach env (``gymnasium.make_vec(id, N,
            vectorization_mode="vector_entry_point")``), wrapped or not.
        control_cost: As for :class:`GoalObservation`.

    Raises:
        TypeError: not the native vector env (a sharded one keeps its targets in its workers), a task that is
            not a reach task, or a vector wrapper inside this one that changes the observation or the info's
            layout (``DictInfoToList``).
    """

    def __init__(self, env: VectorEnv, control_cost: bool = False) -> None:
        VectorWrapper.__init__(self, env)
        self.control_cost = bool(control_cost)
        base = env.unwrapped
        if not isinstance(base, LatentVectorEnv):
            raise TypeError(
                f"GoalVectorObservation needs the native vector env (LatentVectorEnv, one process), got "
                f"{type(base).__name__}"
            )
        _reach_task(base.sim.task, type(base.template).__name__, "GoalVectorObservation")
        own = env.single_observation_space == base.single_observation_space
        changing = (VectorObservationWrapper, DictInfoToList)
        _check_own_observation(env, VectorWrapper, changing, own, "GoalVectorObservation")
        self._split = GoalSplit(base.observation_structure)
        self.single_observation_space = self._split.space(base.single_observation_space)
        self.observation_space = batch_space(self.single_observation_space, self.num_envs)

    @property
    def task(self) -> HandleReach:
        """The vector env's reach task (its distance scale, success radius and bonus set the reward)."""
        return self.env.unwrapped.sim.task

    def _targets(self) -> np.ndarray:
        """Every copy's target [N, k] [m] now."""
        return self.env.unwrapped.sim.params["target"].detach().cpu().numpy().copy()

    def reset(
        self, *, seed: int | Sequence[int | None] | None = None, options: dict[str, Any] | None = None
    ) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        obs, info = self.env.reset(seed=seed, options=options)
        return self._split(obs, self._targets()), info

    def step(self, actions: np.ndarray) -> tuple[dict[str, np.ndarray], np.ndarray, np.ndarray, np.ndarray, dict]:
        base = self.env.unwrapped
        targets = self._targets()  # the goals of the episodes this step continues
        restart = base.autoresetting  # NEXT_STEP: copies this step resets (reward 0)
        obs, reward, terminated, truncated, info = self.env.step(actions)
        ended_obs = obs
        if "final_obs" in info:  # SAME_STEP: the ended copies' last observations, with their episodes' goals
            ended = np.nonzero(info["_final_obs"])[0]
            ended_obs = obs.copy()
            final = info["final_obs"].copy()
            for i in ended:
                ended_obs[i] = final[i]
                final[i] = self._split(final[i], targets[i])
            info = {**info, "final_obs": final}
        if not self.control_cost:
            goal = self._split(ended_obs, targets)
            reward = self.compute_reward(goal["achieved_goal"], goal["desired_goal"], {}).astype(reward.dtype)
            reward[restart] = 0.0
        return self._split(obs, self._targets()), reward, terminated, truncated, info


__all__ = ["GOAL_BLOCK", "GoalObservation", "GoalSplit", "GoalVectorObservation"]
