"""demonstrations: ML-Agents ``.demo`` files (recorded expert steps for imitation learning),
read and written byte-compatibly with Unity's recorder and ML-Agents' ``demo_loader``.

Importing the package activates :mod:`mlagents_compat` first, so that mlagents-envs'
generated protobuf classes import on current protobuf.
"""

import mlagents_compat as _compat

_compat.install()

from demonstrations.demo_file import (  # noqa: E402
    demo_files,
    read_demo,
    read_demos,
    spec_mismatch,
    write_demo,
)
from demonstrations.expert_steps import expert_steps  # noqa: E402
from demonstrations.records import DemoError, DemoMeta, Demonstration, DemoStep  # noqa: E402

__all__ = [
    "DemoError",
    "DemoMeta",
    "DemoStep",
    "Demonstration",
    "demo_files",
    "expert_steps",
    "read_demo",
    "read_demos",
    "spec_mismatch",
    "write_demo",
]
