"""unitysim: a headless program that plays the Unity side of the ML-Agents protocol.

``mlagents_envs.UnityEnvironment`` launches it like a Unity build (``<dir>/<Env>.x86_64``
from ``python -m unitysim build DIR``) or talks to it in editor mode
(``python -m unitysim editor --env 3DBall``). It speaks communication API 1.5.0 over real
gRPC and reproduces the example environments of the reference specs.

unitysim imports nothing of ``rollout`` or ``learners`` except ``mlagents_compat``, the
leaf module that makes mlagents-envs' generated protobuf code import; it is activated
here, before any submodule touches that code.
"""

import mlagents_compat as _compat

_compat.install()
