#!/usr/bin/env bash
# The C core's tests under UndefinedBehaviorSanitizer (CI runs it: .ci/run).
#
# A copy of this checkout (its tracked files, as they are now) gets a venv
# of its own (scripts/setup.sh) and every C extension built again with
# -fsanitize=undefined: an undefined operation (a signed overflow, a shift
# past the width, a misaligned or null-based pointer, an out-of-range enum
# ...) ends the process that met it, and its report, with the stack, is
# written to a file the run then shows; one report fails the run, whichever
# process (the test's, a container's, a node process) met it. About 8
# minutes on a busy 2-core machine: 2 for the venv and the build, 6 for the
# tests. Extra arguments go to pytest.
#
# Not AddressSanitizer: it replaces malloc and keeps a shadow of every
# mapping, where the product is itself a malloc interposer (the allocator
# guard, preloaded) whose node processes share one address space made by
# clone(CLONE_VM); the two cannot both own the heap.
set -euo pipefail
cd "$(dirname "$0")/.."

# The test files that drive the C core, the allocator guard, the herald,
# the crash handler and the repairs directly (their containers too).
TESTS=(
    tests/test_isolated_core.py tests/test_alloc_guard.py tests/test_herald.py
    tests/test_isolated_crash.py tests/test_isolated_jemalloc.py tests/test_isolated_threads.py
    tests/test_pkeys.py tests/test_isolated_container.py tests/test_isolated_interp.py
    tests/test_isolated_gil.py tests/test_isolated_context_lock.py tests/test_python_locks.py
    tests/test_native_mutexes.py tests/test_memory_budget.py tests/test_core_dumps.py
    tests/test_reclaim_container.py
)

copy=$(mktemp -d /var/tmp/cloneguard-ubsan.XXXXXX)
trap 'rm -rf "$copy"' EXIT
git ls-files -z | tar --null -T - -cf - | tar -C "$copy" -xf -
cd "$copy"
echo "== ubsan: a venv for a copy of the checkout in $copy"
./scripts/setup.sh >setup.log 2>&1 || { tail -30 setup.log; exit 1; }
echo "== ubsan: the C extensions again, with -fsanitize=undefined"
CFLAGS="-fsanitize=undefined -fno-sanitize-recover=undefined -fno-omit-frame-pointer -g" \
    LDFLAGS="-fsanitize=undefined" .venv/bin/python setup.py -q build_ext --inplace --force >build.log 2>&1 ||
    { tail -30 build.log; exit 1; }
# build_ext goes on past a module that fails to compile: say why it did.
ldd container/isolated/_clonecore*.so | grep -q libubsan ||
    { echo "ubsan: the C core was built without it:" >&2; grep -i -B3 -A12 "error" build.log | tail -60 >&2; exit 1; }
mkdir reports-ubsan
status=0
UBSAN_OPTIONS="halt_on_error=1:print_stacktrace=1:log_path=$copy/reports-ubsan/ubsan" \
    .venv/bin/python -m pytest "${TESTS[@]}" -q -p no:randomly -o faulthandler_timeout=960 \
    -o faulthandler_exit_on_timeout=true "$@" || status=$?
if compgen -G "reports-ubsan/ubsan.*" >/dev/null; then
    echo "== ubsan: undefined behaviour met (each report names the process's pid):"
    cat reports-ubsan/ubsan.*
    exit 1
fi
echo "== ubsan: no undefined behaviour reported"
exit "$status"
