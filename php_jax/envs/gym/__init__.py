"""Any Gymnasium environment as a php_jax world: observations as vectors and actions as factors (`spaces`),
the environment and expert a command names (`loading`), an expert's episodes recorded as demonstrations
(`recording`), and a learned policy acting in the real environment (`acting`). Their public names are here:
`php_jax.envs.gym.record`, `php_jax.envs.gym.act`, and so on.
"""
from php_jax.envs.gym.acting import act, check_policy, policy_sizes, vector_env
from php_jax.envs.gym.loading import DEFAULT_MAX_STEPS, env_maker, env_observation_fields, expert_maker
from php_jax.envs.gym.recording import record, recorded, write_demonstrations
from php_jax.envs.gym.spaces import (GymError, action_factors, action_sizes, env_actions, flatten_batch,
                                     flatten_observation, observation_fields, observation_size)

__all__ = ["DEFAULT_MAX_STEPS", "GymError", "act", "action_factors", "action_sizes", "check_policy", "env_actions",
           "env_maker", "env_observation_fields", "expert_maker", "flatten_batch", "flatten_observation",
           "observation_fields", "observation_size", "policy_sizes", "record", "recorded", "vector_env",
           "write_demonstrations"]
