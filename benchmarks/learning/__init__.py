"""How a run learns: ``unity-rollout train`` alone, against mlagents-learn on ML-Agents'
own configs (to levels, to fixed steps, a curriculum), steps to a reward without Ray, and
what collecting ahead and policy lag do to learning; ``trainer_runs`` is their shared
part (builds, configs, a trainer run to a level, TensorBoard read back)."""
