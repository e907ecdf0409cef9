"""Gymnasium adapters over one Unity behavior, for users of other RL libraries:
``UnityGymEnv`` (one agent) and ``UnityVectorEnv`` (every agent of a behavior); and
``pettingzoo_env.UnityParallelEnv``, a PettingZoo ParallelEnv over every agent of every
behavior (imported from its module: it loads PettingZoo). See docs/gymnasium.md."""

from gymnasium_adapters.env import AgentSetError, UnityGymEnv, UnityVectorEnv

__all__ = ["AgentSetError", "UnityGymEnv", "UnityVectorEnv"]
