"""Run every benchmark with small counts, then write reports/bench/summary.md.

    python -m cloneguard.bench                              # a few minutes
    python -m cloneguard.bench --only load_latency crash_latency
    python -m cloneguard.bench --preset tiny --out /tmp/b   # a smoke run (seconds per benchmark)

Each benchmark writes its own <name>.md / <name>.json beside summary.md; the
summary's table (one row per measure and mode, with the goal and whether it
was met) is meant to be pasted into bench/README.md.
"""

from __future__ import annotations

import argparse
import shlex
import sys
import traceback
from pathlib import Path
from typing import Any

from . import (
    child_start,
    crash_latency,
    intra,
    load_latency,
    lock_doctor,
    memory,
    message_faults_cost,
    pkeys_cost,
    python_locks,
    scale,
    shutdown,
)
from .cli import DEFAULT_OUT, command_line
from .results import SUMMARY_COLUMNS, Table, host, host_line

BENCHMARKS = {
    "child_start": child_start,
    "memory": memory,
    "crash_latency": crash_latency,
    "load_latency": load_latency,
    "shutdown": shutdown,
    "intra": intra,
    "python_locks": python_locks,
    "lock_doctor": lock_doctor,
    "scale": scale,
    "pkeys_cost": pkeys_cost,
    "message_faults_cost": message_faults_cost,
}
PRESETS: dict[str, dict[str, dict[str, Any]]] = {
    "default": {
        "child_start": {"n": 10, "n_raw": 100},
        "memory": {"nodes": 20, "settle": 1.0},
        "crash_latency": {"n": 20, "n_monitor": 30},
        "load_latency": {"n": 15},
        "shutdown": {"reps": 2, "counts": [1, 5, 20]},
        "intra": {"sizes": ["1KiB", "64KiB", "1MiB", "16MiB"], "count": 100},
        "python_locks": {"rounds": 15, "ops": 200_000},
        "lock_doctor": {"nodes": [1, 10, 40], "threads": 4, "seconds": 5.0},
        "scale": {"counts": [12, 24, 48, 96], "idle": 10.0},
        "pkeys_cost": {"n": 30, "count": 100},
        "message_faults_cost": {"n": 20, "count": 100},
    },
    "tiny": {
        "child_start": {"n": 2, "n_raw": 2},
        "memory": {"nodes": 2, "settle": 0.2, "modes": ["isolated-per-node", "thread", "process-per-node"]},
        "crash_latency": {"n": 2, "n_monitor": 2, "settle": 0.02},
        "load_latency": {"n": 2, "modes": ["isolated-per-node", "thread"]},
        "shutdown": {"reps": 1, "counts": [1, 2], "settle": 0.1, "modes": ["isolated-per-node", "thread"]},
        "intra": {"sizes": ["1KiB", "1MiB"], "count": 2, "warmup": 1, "burst": 5, "burst_seconds": 0.5, "settle": 0.2},
        "python_locks": {"rounds": 3, "ops": 2000},
        "lock_doctor": {"nodes": [1, 2], "threads": 1, "seconds": 0.5, "resident": [0, 64]},
        "scale": {
            "counts": [1, 2],
            "idle": 0.3,
            "settle": 0.1,
            "modes": ["thread", "isolated-per-node", "process-per-node"],
        },
        "pkeys_cost": {"n": 2, "count": 2, "pairs": 20_000, "repeat": 1},
        "message_faults_cost": {"n": 1, "count": 2},
    },
}


def summary_markdown(results: dict, failures: dict, command: str) -> str:
    table = Table("Benchmarks", SUMMARY_COLUMNS)
    for name in BENCHMARKS:
        if name in results:
            for row in results[name].summary:
                table.add(*(row[c] for c in SUMMARY_COLUMNS))
    info = next(iter(results.values())).host if results else host()
    out = [
        "# Benchmarks: summary",
        "",
        f"Command (from the repository root, venv active): `{command}`",
        "",
        f"Host: {host_line(info)}",
        "",
        "Medians and p90 measured side by side in one run on this host; ratios are of medians. "
        "Details, methods and the exact command of each: the `<benchmark>.md` files beside this one.",
        "",
        table.markdown(),
        "",
    ]
    if failures:
        out += ["Failed: " + "; ".join(f"{name}: {err}" for name, err in failures.items()), ""]
    dirty = [f"{name}: {'; '.join(r.cleanup)}" for name, r in results.items() if r.cleanup]
    out += [
        "Clean-up: "
        + (
            "every benchmark stopped all it started; no process or /dev/shm segment left."
            if not dirty
            else "PROBLEMS: " + " | ".join(dirty)
        ),
        "",
    ]
    return "\n".join(out)


def run_all(
    *,
    preset: str = "default",
    only: list[str] | None = None,
    out=DEFAULT_OUT,
    keep_logs: bool = False,
    quiet: bool = False,
    command: str | None = None,
):
    """Run the benchmarks; return (results by name, failures by name, summary path)."""
    out = Path(out)
    results, failures = {}, {}
    for name, module in BENCHMARKS.items():
        if only and name not in only:
            continue
        params = dict(PRESETS[preset][name])
        if not quiet:
            print(f"\n=== {name}: {command_line(name, params)}\n", flush=True)
        try:
            results[name] = module.run(out=out, keep_logs=keep_logs, quiet=quiet, **params)
        except Exception as exc:  # the others still run; the summary says what failed
            traceback.print_exc()
            failures[name] = f"{type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''}"
    command = command or shlex.join(
        ["python", "-m", "cloneguard.bench", "--preset", preset] + (["--only", *only] if only else [])
    )
    text = summary_markdown(results, failures, command)
    path = out / "summary.md"
    out.mkdir(parents=True, exist_ok=True)
    path.write_text(text)
    if not quiet:
        print("\n" + text)
        print(f"wrote {path}")
    return results, failures, path


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m cloneguard.bench", description=__doc__.split("\n")[0])
    parser.add_argument(
        "--preset", choices=list(PRESETS), default="default", help="counts to run with (default: %(default)s)"
    )
    parser.add_argument("--only", nargs="+", choices=list(BENCHMARKS), default=None)
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT)
    parser.add_argument("--keep-logs", action="store_true")
    opts = parser.parse_args(argv)
    results, failures, _ = run_all(preset=opts.preset, only=opts.only, out=opts.out, keep_logs=opts.keep_logs)
    return 1 if failures or any(r.cleanup for r in results.values()) else 0


if __name__ == "__main__":
    sys.exit(main())
