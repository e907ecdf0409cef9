"""The training algorithms, one module each (PPO, POCA, SAC, IMPALA, their recurrent and self-play
variants), and the on-policy machinery they share."""
