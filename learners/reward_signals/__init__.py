"""Rewards: the extrinsic one, curiosity, RND, GAIL and behavioral cloning, and how PPO and SAC
carry them as value or Q streams."""
