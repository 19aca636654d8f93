#!/usr/bin/env bash
# The project's tests: unit and integration tests of the code (tests/; the
# scenarios are the main job, README). Extra arguments go to pytest.
#
# Many tests run clone children inside the test process itself. A repair
# that cannot finish there can leave the GIL held for good; pytest-timeout's
# SIGALRM handler then never runs, and the run would sit silent until CI's
# own time-out. pytest's faulthandler needs no GIL: past 960 s in one test
# (above the longest per-test timeout, 900 s) it prints every thread's
# Python stack and ends the run with status 1.
set -euo pipefail
cd "$(dirname "$0")/.."
exec .venv/bin/python -m pytest tests -o faulthandler_timeout=960 -o faulthandler_exit_on_timeout=true "$@"
