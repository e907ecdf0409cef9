"""Choose torch's wheel index for an image build, and stop the build early when the build of
torch it asks for cannot be had.

The build argument TORCH names the build: ``cpu`` (the default), a CUDA build of the pinned
torch (``cu126``, ``cu130``, ``cu132``: those wheels carry their CUDA runtime as nvidia-*
packages, so no CUDA base image is needed), or ``any``. pip takes torch from that build's
index (``PIP_EXTRA_INDEX_URL``) when it is reachable; when it is not, pip silently installs
whatever the package registry has (for a CPU image: the CUDA build, ~3 GB with its nvidia
libraries), after slow retries. Standard library only: it runs before the virtual
environment exists.

    python3 scripts/check-torch-index.py --index-for TORCH [INDEX_URL]
        # the index to build with: INDEX_URL, else torch's own for TORCH; a TORCH that is not
        # a build of this image stops here, with one line naming the builds
    python3 scripts/check-torch-index.py [--torch TORCH] INDEX_URL
        # before the install: does INDEX_URL have TORCH's wheel of the pinned torch?
    python scripts/check-torch-index.py [--torch TORCH] --installed
        # after: is the installed torch that build?

TORCH defaults to cpu; with ``any`` nothing is checked. Errors go to stderr, one line each.
"""

from __future__ import annotations

import re
import sys
import urllib.request
from pathlib import Path

CONSTRAINTS = Path(__file__).resolve().parents[1] / "constraints.txt"

# The builds torch publishes for the pinned release (torch 2.13: CUDA 12.6 and 13.0 stable,
# 13.2 experimental; 13.0 is also the build on the package registry). A new torch pin
# revisits this table (tests/deploy/test_torch_index.py fails until it does).
TORCH_SERIES = "2.13"
BUILDS = {"cpu": "CPU", "cu126": "CUDA 12.6", "cu130": "CUDA 13.0", "cu132": "CUDA 13.2"}
ANY = "any"
TORCH_INDEX = "https://download.pytorch.org/whl/"


def pinned_torch() -> str:
    for line in CONSTRAINTS.read_text().splitlines():
        if line.startswith("torch=="):
            return line.split("==", 1)[1].strip()
    raise SystemExit(f"error: {CONSTRAINTS} pins no torch version")


def build_problem(torch: str) -> str | None:
    """None when TORCH names a build of this image, else the one-line error."""
    if torch in BUILDS or torch == ANY:
        return None
    *cuda, last = (build for build in BUILDS if build != "cpu")
    return (
        f"error: --build-arg TORCH={torch}: no such build of torch {TORCH_SERIES}; use cpu "
        f"(the default), {', '.join(cuda)} or {last} (CUDA), or {ANY}"
    )


def index_for(torch: str, given: str = "") -> str:
    """The extra index of a build: GIVEN (a mirror) when set, else torch's own for TORCH
    (``any``: the CPU one, so that pip still prefers the CPU wheel where it can have it)."""
    if given.strip():
        return given.strip()
    return TORCH_INDEX + ("cpu" if torch == ANY else torch)


def check_index(index: str, torch: str = "cpu") -> str | None:
    """None when INDEX lists this Python's TORCH wheel of the pinned torch, else the problem."""
    version, tag = pinned_torch(), f"cp{sys.version_info[0]}{sys.version_info[1]}"
    url = index.rstrip("/") + "/torch/"
    try:
        with urllib.request.urlopen(url, timeout=30) as response:
            page = response.read().decode("utf-8", "replace")
    except OSError as error:
        return f"{url} is unreachable ({getattr(error, 'reason', error)})"
    wheel = re.compile(rf"torch-{re.escape(version)}(%2B|\+){re.escape(torch)}-{tag}-{tag}-")
    if not wheel.search(page):
        return f"{url} has no torch-{version}+{torch} wheel for {tag}"
    return None


def installed_build() -> tuple[str, str, str]:
    """The installed torch: its version, its build as TORCH names it (cpu, cu130, ...) and
    that build in words."""
    import torch

    cuda = torch.version.cuda
    if cuda is None:
        return torch.__version__, "cpu", "CPU"
    return torch.__version__, "cu" + cuda.replace(".", ""), f"CUDA {cuda}"


def hint(torch: str) -> str:
    text = (
        "pass --build-arg PIP_EXTRA_INDEX_URL=<an index that has it>, or --build-arg TORCH=any "
        "to accept whichever torch build pip finds"
    )
    return text + (" (CUDA: ~3 GB more)" if torch == "cpu" else "")


def fail(message: str, status: int = 1) -> int:
    print(message, file=sys.stderr)
    return status


def main(argv: list[str]) -> int:
    args = list(argv)
    if args[:1] == ["--index-for"] and len(args) in (2, 3):
        problem = build_problem(args[1])
        if problem:
            return fail(problem, 2)
        print(index_for(args[1], args[2] if len(args) == 3 else ""))
        return 0
    torch = "cpu"
    if args[:1] == ["--torch"] and len(args) >= 2:
        torch, args = args[1], args[2:]
        problem = build_problem(torch)
        if problem:
            return fail(problem, 2)
    if len(args) != 1 or (args[0].startswith("--") and args[0] != "--installed"):
        print(__doc__, file=sys.stderr)
        return 2
    if torch == ANY:
        return 0
    wanted = BUILDS[torch]
    if args == ["--installed"]:
        version, build, found = installed_build()
        if build != torch:
            return fail(
                f"error: torch {version} ({found}) was installed for an image of torch's "
                f"{wanted} build (TORCH={torch}); {hint(torch)}"
            )
        return 0
    problem = check_index(args[0], torch)
    if problem:
        return fail(
            f"error: torch's {wanted} build is asked for (TORCH={torch}) but {problem}; "
            f"{hint(torch)}"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
