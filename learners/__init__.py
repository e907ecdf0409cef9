"""learners: everything that trains, by role: ``trainer_config`` (ML-Agents' trainer YAML),
``networks`` (torch networks from a ``BehaviorSpec``), ``algorithms`` (PPO, POCA, SAC, IMPALA
and their variants), ``reward_signals`` (extrinsic, curiosity, RND, GAIL, cloning), ``acting``
(the numpy policy a worker acts with) and ``host`` (the central learner, its Ray shell,
device, checkpoints and export). Imports nothing of ours but ``batches``."""
