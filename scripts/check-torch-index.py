"""Stop an image build early when the CPU build of torch cannot be had.

pip takes torch's CPU wheel from the extra index (``PIP_EXTRA_INDEX_URL``) when it is
reachable; when it is not, pip silently installs the CUDA build from the package registry
instead (~3 GB with its nvidia libraries), after slow retries. Standard library only: it
runs before the virtual environment exists.

    python3 scripts/check-torch-index.py INDEX_URL   # before the install: is the wheel there?
    python scripts/check-torch-index.py --installed  # after: is the installed torch CPU-only?
"""

from __future__ import annotations

import re
import sys
import urllib.request
from pathlib import Path

CONSTRAINTS = Path(__file__).resolve().parents[1] / "constraints.txt"


def pinned_torch() -> str:
    for line in CONSTRAINTS.read_text().splitlines():
        if line.startswith("torch=="):
            return line.split("==", 1)[1].strip()
    raise SystemExit(f"error: {CONSTRAINTS} pins no torch version")


def check_index(index: str) -> str | None:
    """None when INDEX lists this Python's CPU wheel of the pinned torch, else the problem."""
    version, tag = pinned_torch(), f"cp{sys.version_info[0]}{sys.version_info[1]}"
    url = index.rstrip("/") + "/torch/"
    try:
        with urllib.request.urlopen(url, timeout=30) as response:
            page = response.read().decode("utf-8", "replace")
    except OSError as error:
        return f"{url} is unreachable ({getattr(error, 'reason', error)})"
    wheel = re.compile(rf"torch-{re.escape(version)}(%2B|\+)cpu-{tag}-{tag}-")
    if not wheel.search(page):
        return f"{url} has no torch-{version}+cpu wheel for {tag}"
    return None


def main(argv: list[str]) -> int:
    hint = (
        "pass --build-arg PIP_EXTRA_INDEX_URL=<an index that has it>, or --build-arg TORCH=any "
        "to accept whichever torch build pip finds (CUDA: ~3 GB more)"
    )
    if argv == ["--installed"]:
        import torch

        if torch.version.cuda is not None:
            print(f"error: torch {torch.__version__} (CUDA) was installed for a CPU image; {hint}")
            return 1
        return 0
    if len(argv) != 1:
        print(__doc__, file=sys.stderr)
        return 2
    problem = check_index(argv[0])
    if problem:
        print(f"error: torch's CPU build is asked for (TORCH=cpu) but {problem}; {hint}")
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
