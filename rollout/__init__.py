"""rollout: the actor side of unity-rollout (ports, Unity processes, workers, service, CLI).

Importing the package activates :mod:`rollout.compat` first, so every module below may
import mlagents_envs directly; nothing is activated merely by installing the package.
"""

from rollout import compat as _compat

_compat.install()
