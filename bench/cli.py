"""A benchmark as a command: its options, the command line that repeats a
run, and the end of a run (the report written and printed)."""

from __future__ import annotations

import argparse
import shlex
from pathlib import Path

from cloneguard.harness.process import REPO_ROOT

from .results import Result

DEFAULT_OUT = REPO_ROOT / "reports" / "bench"


def arg_parser(name: str, description: str) -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog=f"python -m cloneguard.bench.{name}", description=description)
    parser.add_argument(
        "--out", type=Path, default=DEFAULT_OUT, help="directory for <name>.md and <name>.json (default: reports/bench)"
    )
    parser.add_argument("--keep-logs", action="store_true", help="keep the container logs (their directory is printed)")
    return parser


def command_line(name: str, args: dict) -> str:
    """The command that repeats a run with these parameters."""
    parts = ["python", "-m", f"cloneguard.bench.{name}"]
    for key, value in args.items():
        flag = "--" + key.replace("_", "-")
        if isinstance(value, bool):
            if value:
                parts.append(flag)
        elif isinstance(value, (list, tuple)):
            parts += [flag, *[str(v) for v in value]]
        else:
            parts += [flag, str(value)]
    return shlex.join(parts)


def finish(result: Result, out_dir: Path, *, quiet: bool = False) -> Result:
    md, js = result.write(out_dir)
    if not quiet:
        print(result.markdown())
        print(f"wrote {md} and {js}")
    return result
