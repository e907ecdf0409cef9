"""``unity-rollout tune``: many runs as Ray Tune trials (search space, PBT, one trial)."""
