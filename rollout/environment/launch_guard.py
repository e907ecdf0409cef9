"""``python -m rollout.environment.launch_guard EXE [ARGS...]``: exec a Unity player tied to its
parent.

mlagents_envs starts players with ``start_new_session=True``, so a worker killed with
SIGKILL would leave its player running. This tiny wrapper asks Linux to SIGKILL it when
its parent dies (``PR_SET_PDEATHSIG``, which survives ``exec``), checks the parent did
not die first, then becomes the player. Elsewhere it just execs.
"""

from __future__ import annotations

import ctypes
import os
import signal
import sys

PR_SET_PDEATHSIG = 1


def main(argv: list[str]) -> None:
    if not argv:
        sys.exit("usage: python -m rollout.environment.launch_guard EXECUTABLE [ARGS...]")
    parent = os.getppid()
    if sys.platform.startswith("linux"):
        libc = ctypes.CDLL(None, use_errno=True)
        if libc.prctl(PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0) != 0:
            sys.exit(f"launch_guard: prctl failed: {os.strerror(ctypes.get_errno())}")
        if os.getppid() != parent:  # the parent died before the guard was armed
            sys.exit(1)
    os.execv(argv[0], argv)


if __name__ == "__main__":
    main(sys.argv[1:])
