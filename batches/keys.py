"""Every TensorDict key of a segment, in one place (see docs/batch-format.md).

torchrl conventions: what follows an action (reward, done flags, next observation) lives
under ``"next"`` with a trailing dimension of 1 for scalars. Action masks follow torchrl's
``MaskedCategorical`` convention, True = allowed, the inverse of ML-Agents' wire flag.
"""

from __future__ import annotations

OBS = "obs"  # ("obs", <sensor name>): float32 [*sensor shape] (PNG sensors: uint8), per sensor
ACTION = "action"  # ("action", CONTINUOUS) float32 [c]; ("action", DISCRETE) int64 [branches]
CONTINUOUS = "continuous"
DISCRETE = "discrete"
ACTION_MASK = "action_mask"  # bool [sum(branches)], True = allowed; discrete behaviors only
# float32 [continuous + branches]: log-probability of each action component (each
# continuous dimension, then each branch) under the acting policy; the action's is their sum
LOG_PROB = "sample_log_prob"
# float32 [memory_size]: a recurrent policy's memory as the agent's decision read it (its
# LSTM's hidden, then cell state; zeros at an episode's start); only for such a policy
MEMORY = "memory"
POLICY_VERSION = "policy_version"  # int64: version of the weights that chose the action
AGENT_ID = "agent_id"  # int64: Unity's agent id (unique within a behavior)
GROUP_ID = "group_id"  # int64: multi-agent group, 0 = none
# (GROUPMATES, ...): the other members of the agent's group at this step, [M, ...] per step
# (M: the most a segment has; absent places are zeros with PRESENT False): OBS (what each
# acted on), ACTION, REWARD and DONE (of its latest report), PRESENT; and
# (NEXT, GROUPMATES, OBS): their newest observations, for the bootstrap (POCA)
GROUPMATES = "groupmates"
PRESENT = "present"

NEXT = "next"
REWARD = "reward"  # ("next", REWARD) float32 [1]: reward since the decision
GROUP_REWARD = "group_reward"  # ("next", GROUP_REWARD) float32 [1]
DONE = "done"  # ("next", DONE) bool [1]: the episode ended after this step
TERMINATED = "terminated"  # ("next", TERMINATED): ended for real (bootstrap with 0)
TRUNCATED = "truncated"  # ("next", TRUNCATED): interrupted (MaxStep) or cut: bootstrap
# ("next", CUT) bool [1]: truncated at a row's end while the episode goes on (a horizon);
# optional (absent: none): an episode ended where ``done`` and not ``CUT``
CUT = "cut"

# Segment metadata, one value per row (batch dimension only).
WORKER = "worker"  # int64: index of the worker that collected the row
ENV_STEPS = "env_steps"  # int64: the worker's environment exchanges when the row was emitted
BEHAVIOR = "behavior"  # non-tensor str: the fully qualified behavior name
SPEC = "behavior_spec"  # non-tensor dict: specs.spec_to_dict(BehaviorSpec), for the learner
METADATA = (BEHAVIOR, SPEC)  # the non-tensor entries; exclude them before tensor maths
