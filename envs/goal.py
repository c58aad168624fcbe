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
    env = GoalObservation(gym.make("RedSim/MiniChain-v0"))
    SAC("MultiInputPolicy", env, replay_buffer_class=HerReplayBuffer).learn(10_000)

The reward depends on the goals alone, -d / L + bonus [d < r] (:class:`HandleReach`'s distance and success terms),
as HER needs: SB3's ``HerReplayBuffer`` relabels with empty ``info`` dicts unless asked to copy them. So the wrapper
leaves out the task's control cost (still reported in ``info["reward_control"]``) and returns this reward from
``step`` too. ``GoalObservation(env, control_cost=True)`` keeps it: the reward is then the env's own, and
``compute_reward`` reads the control term from the ``info`` of each transition (SB3:
``replay_buffer_kwargs={"copy_info_dict": True}``).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from redsim.envs.reach import HandleReach

GOAL_BLOCK = "target_offset"
"""The observation block that depends on the desired goal: left out of ``"observation"``."""


class GoalObservation(gym.ObservationWrapper, gym.utils.RecordConstructorArgs):
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
        task = getattr(base, "task", None)
        if not isinstance(task, HandleReach):
            raise TypeError(
                f"GoalObservation needs a reach env (task HandleReach), got task {type(task).__name__} of "
                f"{type(base).__name__}; reach envs: MiniChain, Chain, ClothBall, HangingCloth, ConditionalBar"
            )
        inner = env
        while isinstance(inner, gym.Wrapper):  # the split below reads the env's own observation
            if isinstance(inner, (gym.ObservationWrapper, gym.wrappers.NormalizeObservation)):
                raise TypeError(
                    f"GoalObservation must wrap the env's own observation, but {type(inner).__name__} changes it; "
                    "put observation wrappers outside GoalObservation"
                )
            inner = inner.env
        if env.observation_space != base.observation_space:
            raise TypeError("GoalObservation needs the env's own flat Box observation")
        blocks, start = {}, 0
        for name, size in base.observation_structure.items():
            blocks[name] = slice(start, start + size)
            start += size
        self._achieved = blocks["handle_position"]
        self._keep = np.concatenate([np.arange(s.start, s.stop) for n, s in blocks.items() if n != GOAL_BLOCK])
        flat = base.observation_space
        goal = spaces.Box(flat.low[self._achieved], flat.high[self._achieved], dtype=np.float32)
        self.observation_space = spaces.Dict(
            {
                "observation": spaces.Box(flat.low[self._keep], flat.high[self._keep], dtype=np.float32),
                "achieved_goal": goal,
                "desired_goal": goal,
            }
        )

    @property
    def task(self) -> HandleReach:
        """The env's reach task (its distance scale, success radius and bonus set the reward)."""
        return self.env.unwrapped.task

    def step(self, action: Any) -> tuple[dict[str, np.ndarray], float, bool, bool, dict[str, Any]]:
        obs, _, terminated, truncated, info = super().step(action)
        reward = float(self.compute_reward(obs["achieved_goal"], obs["desired_goal"], info))
        return obs, reward, terminated, truncated, info

    def observation(self, observation: np.ndarray) -> dict[str, np.ndarray]:
        target = self.env.unwrapped.sim.params["target"][0]
        return {
            "observation": observation[self._keep],
            "achieved_goal": observation[self._achieved],
            "desired_goal": target.detach().cpu().numpy().astype(np.float32),
        }

    def compute_reward(
        self, achieved_goal: np.ndarray, desired_goal: np.ndarray, info: Mapping[str, Any] | Sequence[Mapping[str, Any]]
    ) -> np.ndarray:
        """The reward for goals [..., k] (float32, shape [...]); ``info``: one step's info dict, or one per goal (a
        sequence or object array of shape [...], as SB3's HER passes them); read only with ``control_cost``.

        Raises:
            KeyError: ``control_cost`` and an ``info`` without ``"reward_control"`` (SB3's HER copies none unless
                ``copy_info_dict=True``).
        """
        achieved = np.asarray(achieved_goal, dtype=np.float64)
        desired = np.asarray(desired_goal, dtype=np.float64)
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


__all__ = ["GOAL_BLOCK", "GoalObservation"]
