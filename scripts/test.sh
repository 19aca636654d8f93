#!/usr/bin/env bash
# The project's tests: unit and integration tests of the code (tests/; the
# scenarios are the main job, README). Extra arguments go to pytest.
set -euo pipefail
cd "$(dirname "$0")/.."
exec .venv/bin/python -m pytest tests "$@"
