#!/usr/bin/env bash
# The project's machine-checked style (CI runs it: .ci/run): ruff (lint and
# format) over every Python file, mypy over the product and the harness.
# The C is built with -Wall -Wextra -Werror (scripts/cflags.py) by setup.sh.
set -euo pipefail
cd "$(dirname "$0")/.."
.venv/bin/ruff check .
.venv/bin/ruff format --check .
.venv/bin/mypy container harness
