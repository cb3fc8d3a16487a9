#!/bin/sh
# An agent-only install of this tree, as a companion computer gets it (issue 29: the agent's
# footprint is measured on it): the wheel built from a copy of the tree, installed with its
# dependencies alone (pydantic, pymavlink, pyserial) into a clean venv, byte-compiled as pip does.
#   bench/agent_venv.sh /tmp/agent-venv && python bench/bench_load.py --only-agent mavlink --agent-bin /tmp/agent-venv/bin
set -eu
VENV=${1:?usage: bench/agent_venv.sh VENV_DIR}
HERE=$(cd "$(dirname "$0")/.." && pwd)
PY=${PYTHON:-python3}
WORK=$(mktemp -d)
trap 'rm -rf "$WORK"' EXIT
mkdir "$WORK/src"
for part in protocol gcs agent sitl pyproject.toml README.md; do
    cp -r "$HERE/$part" "$WORK/src/"
done
find "$WORK/src" -name __pycache__ -prune -exec rm -rf {} +
"$PY" -m pip wheel --no-deps --no-build-isolation -q -w "$WORK/dist" "$WORK/src"
rm -rf "$VENV"
"$PY" -m venv --without-pip "$VENV"
"$PY" -m pip --python "$VENV/bin/python" install -q --disable-pip-version-check "$WORK"/dist/fleetgcs-*.whl
echo "$VENV/bin/agent"
