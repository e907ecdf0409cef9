"""learners: the trainer config, the networks, PPO / SAC / IMPALA, the central learner and
its Ray shell, checkpoints and ONNX export. Imports nothing of ours but ``batches``."""
