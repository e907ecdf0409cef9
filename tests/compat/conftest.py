"""The compat tests need only mlagents-envs, protobuf, grpcio, numpy and Pillow.

They also run under other interpreters (tests/compat/test_interpreters.py), so nothing
here may import torch, ray or our heavier packages.
"""

import mlagents_compat as compat

compat.install()
