"""Tests of unitysim; activating the compat layer before any test imports mlagents_envs."""

from rollout import compat

compat.install()
