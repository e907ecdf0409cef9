"""rollout: the actor side of unity-rollout (ports, Unity processes, workers) and the service.

Importing the package activates :mod:`mlagents_compat` first, so every module below may
import mlagents_envs directly; nothing is activated merely by installing the package.
"""

import mlagents_compat as _compat

_compat.install()
