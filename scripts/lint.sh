#!/usr/bin/env bash
# The project's machine-checked style (CI runs it: .ci/run): ruff (lint and
# format) over every Python file, mypy over the product, the harness, the
# faults, the benchmarks and the tests, clang-format over the C
# (.clang-format; an apt package, setup.sh installs it). The C is built with
# scripts/cflags.py's warnings and -Werror by setup.sh.
set -euo pipefail
cd "$(dirname "$0")/.."
.venv/bin/ruff check .
.venv/bin/ruff format --check .
.venv/bin/mypy container harness faults bench tests
git ls-files -z --cached --others --exclude-standard '*.c' '*.h' '*.cpp' | xargs -0 clang-format --dry-run --Werror
