"""rollout: the actor side of unity-rollout, by role: ``environment`` (one Unity instance: its
build, port, process and restarts), ``collecting`` (a worker stepping it, acting and packing
segments) and ``serving`` (the service between the workers and the learner).

Importing the package activates :mod:`mlagents_compat` first, so every module below may
import mlagents_envs directly; nothing is activated merely by installing the package.
"""

import mlagents_compat as _compat

_compat.install()
