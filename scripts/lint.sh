#!/usr/bin/env bash
# The project's machine-checked style (CI runs it: .ci/run): ruff (lint and
# format) over every Python file, mypy over the product, the harness, the
# faults, the benchmarks and the tests (below), clang-format over the C
# (.clang-format; an apt package, setup.sh installs it). The C is built with
# scripts/cflags.py's warnings and -Werror by setup.sh.
set -euo pipefail
cd "$(dirname "$0")/.."
.venv/bin/ruff check .
.venv/bin/ruff format --check .
# mypy reads the code under the names it is imported by (cloneguard.container,
# cloneguard.harness, ...: setup.py and rig/pyproject.toml map them onto this
# tree through editable-install import hooks, which mypy cannot follow). A
# directory of links gives it those names; checked as container.* instead,
# every call made through a cloneguard.* import went unchecked.
names=$(mktemp -d)
trap 'rm -rf "$names"' EXIT
mkdir "$names/cloneguard"
for package in container harness faults bench; do ln -s "$PWD/$package" "$names/cloneguard/$package"; done
MYPYPATH=$names .venv/bin/mypy "$names/cloneguard" tests | sed "s|$names/cloneguard/||"
git ls-files -z --cached --others --exclude-standard '*.c' '*.h' '*.cpp' | xargs -0 clang-format --dry-run --Werror
