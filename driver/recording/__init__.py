"""``unity-rollout record-demo``: one Unity instance played by a policy or a scripted expert,
written to a ``.demo`` file."""
