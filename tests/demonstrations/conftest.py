"""mlagents-envs' generated protobuf classes import only once ``mlagents_compat`` is active;
the test modules import them before ``demonstrations`` (which would activate it too)."""

import mlagents_compat as compat

compat.install()
