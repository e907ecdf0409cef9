"""Tests of unitysim; activating the compat layer before any test imports mlagents_envs."""

import mlagents_compat as compat

compat.install()
