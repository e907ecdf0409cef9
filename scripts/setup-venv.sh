#!/usr/bin/env bash
# Create or reuse the project's virtual environment; reinstall only when its inputs change.
#
# mlagents-envs 1.1.0 declares Python<=3.10.12, protobuf<3.21, grpcio<=1.48.2 and
# numpy<1.24. We install it with --no-deps --ignore-requires-python from the same pin
# file, next to current versions of what it really needs (listed in pyproject.toml);
# mlagents_compat then makes its generated protobuf code import (see README).
set -euo pipefail
cd "$(dirname "$0")/.."

PYTHON=${PYTHON:-python3.11}
VENV=${VENV:-.venv}
EXTRAS=${EXTRAS-dev}  # EXTRAS= (empty): runtime only
inputs=(pyproject.toml setup.py constraints.txt scripts/setup-venv.sh unitysim/envs/_ball3d.c)
# A C compiler appearing (or going) changes what setup.py builds: reinstall then too.
compiler=$(command -v "${CC:-cc}" >/dev/null && echo cc || echo no-cc)
want="$(cat "${inputs[@]}" | sha256sum | cut -c1-16)-$EXTRAS-$compiler"

if [[ -f "$VENV/.installed" && "$(cat "$VENV/.installed")" == "$want" ]]; then
    exit 0
fi
if [[ ! -x "$VENV/bin/python" ]]; then
    echo "setup-venv: creating $VENV with $PYTHON" >&2
    "$PYTHON" -m venv "$VENV"
fi
echo "setup-venv: installing pinned dependencies into $VENV" >&2
pip=("$VENV/bin/python" -m pip --disable-pip-version-check -q)
target="."
[[ -n "$EXTRAS" ]] && target=".[$EXTRAS]"  # the image installs without the dev extras
"${pip[@]}" install -c constraints.txt -e "$target" 2> >(grep -v "is ignored: it is neither a file" >&2)
"${pip[@]}" install -c constraints.txt --no-deps --ignore-requires-python mlagents-envs \
    2> >(grep -v "is ignored: it is neither a file" >&2)
"$VENV/bin/python" -c "import mlagents_compat as c; c.install(); import mlagents_envs.environment"
echo "$want" > "$VENV/.installed"
echo "setup-venv: ready" >&2
