"""``python -m cloneguard.harness reproduce FAULT``: replay a fault until it does not
survive, then stop right there with the container still running, print the
diagnosis, and say how to attach a debugger.

    python -m cloneguard.harness reproduce sigkill-during-malloc --allocator glibc --seed 7 --trials 200
    python -m cloneguard.harness reproduce segfault-gil-held --profile shared --trial-seed 123456

Every fault the scenarios inject can be replayed: the faults come from the
registry the test rig's faults package declares (entry point group
``cloneguard.trials``), the one the scenarios take their trials from.

A scenario of your own (seeded trials of a System: system_trials.py) is
replayed by its pytest node id, run by pytest with the same options, which
stops at its first trial that does not survive and holds its container:

    python -m cloneguard.harness reproduce scenarios/test_robot.py::test_planner --trial-seed 746315781
    python -m cloneguard.harness reproduce scenarios/test_robot.py::test_planner --trials 200 \
        --container-arg=--allocator=glibc

and a fault a package of yours declares by name (named_faults.py, entry
point group ``cloneguard.harness.faults``) the same way, by its name:

    python -m cloneguard.harness reproduce planner-holding-a-lock --trials 200
"""

from __future__ import annotations

import argparse
import os
import random
import shutil
import signal
import subprocess
import sys
import tempfile
from importlib.metadata import entry_points
from pathlib import Path

from cloneguard.harness import domains, named_faults
from cloneguard.harness.factory import ContainerFactory
from cloneguard.harness.memory_cgroup import MemoryCgroupUnavailable
from cloneguard.harness.plan import trial_count_arg
from cloneguard.harness.process import use_loopback_ros
from cloneguard.harness.rig import PROFILES, Outcome, Rig

from .report.model import TrialOutcome

REGISTRY_GROUP = "cloneguard.trials"


def registry() -> tuple[dict, dict]:
    """(fault name -> make(rig), allocator set-up -> container arguments)."""
    found = {ep.name: ep for ep in entry_points(group=REGISTRY_GROUP)}
    missing = {"faults", "allocators"} - set(found)
    if missing:
        raise SystemExit(
            f"no fault registry installed (entry points {sorted(missing)} of "
            f"{REGISTRY_GROUP}: the test rig's faults package)"
        )
    return found["faults"].load(), found["allocators"].load()


def add_parser(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    faults, allocators = registry()
    p = subparsers.add_parser(
        "reproduce",
        help="replay a fault until it does not survive, then stop there",
        description=__doc__.split("\n\n")[0],
    )
    p.add_argument(
        "fault",
        metavar="FAULT|NODE_ID",
        help=f"a fault of the rig ({', '.join(sorted(faults))}), a fault of yours by name "
        f"({', '.join(named_faults.names()) or f'none declared in {named_faults.GROUP}'}), or the pytest "
        "node id of a scenario of yours (path.py::test_name)",
    )
    p.add_argument("--profile", choices=sorted(PROFILES), default=None, help="a rig fault's profile (per-node)")
    p.add_argument(
        "--allocator",
        choices=sorted(allocators),
        default=None,
        help="a rig fault's allocator set-up (default: the container's own, guarded)",
    )
    p.add_argument(
        "--container-arg",
        action="append",
        default=[],
        metavar="ARG",
        help="a scenario of yours: one more container argument (repeat it; --container-arg=--allocator=glibc)",
    )
    p.add_argument("--seed", type=int, default=1, help="base seed; each trial's seed is drawn from it")
    p.add_argument(
        "--trial-seed",
        type=int,
        default=None,
        help="a rig fault: run every trial with this one seed; a scenario of yours: its one trial of this seed",
    )
    p.add_argument(
        "--trials", type=trial_count_arg, default=100, metavar="N", help="at most N (>= 1) trials (default 100)"
    )
    p.add_argument(
        "--container-exe",
        default=None,
        metavar="PATH",
        help="the component container executable to test (default: this project's component_container)",
    )
    p.add_argument(
        "--no-wait",
        action="store_true",
        help="stop the stuck container at once instead of holding it until Ctrl-C",
    )
    p.set_defaults(func=run)


def is_node_id(target: str) -> bool:
    """A pytest node id (a test file, or file::test), not a fault's name."""
    return "::" in target or target.endswith(".py")


def run(args: argparse.Namespace) -> int:
    if is_node_id(args.fault):
        return run_scenario(args)
    if args.fault in named_faults.names():
        if args.fault in registry()[0]:
            raise SystemExit(f"{args.fault!r} is both a fault of the rig's and one declared in {named_faults.GROUP}")
        return run_scenario(args)
    if args.container_arg:
        raise SystemExit("--container-arg is for a scenario of yours; a rig fault takes --profile and --allocator")
    faults, allocators = registry()
    if args.fault not in faults:
        yours = ", ".join(named_faults.names()) or f"none is declared in {named_faults.GROUP}"
        raise SystemExit(f"no fault {args.fault!r}: the rig's are {', '.join(sorted(faults))}; yours: {yours}")
    args.profile = args.profile or "per-node"
    use_loopback_ros()
    log_dir = Path(tempfile.mkdtemp(prefix="cloneguard-reproduce-"))
    print(f"logs: {log_dir} (kept if a trial does not survive)", flush=True)
    rng = random.Random(args.seed)
    survived = False
    with domains.lease() as lease:
        factory = ContainerFactory(lease.domain_id, log_dir, exe=args.container_exe)
        try:
            try:
                rig = Rig(factory, args.profile, extra_args=allocators[args.allocator] if args.allocator else [])
                fault = faults[args.fault](rig)
            except MemoryCgroupUnavailable as why:  # an out-of-memory fault's rig: never without a limit
                raise SystemExit(f"{args.fault} needs a memory cgroup, and none can be made here: {why}") from None
            for i in range(args.trials):
                seed = args.trial_seed if args.trial_seed is not None else rng.getrandbits(31)
                out = fault.trial(seed, i)
                lat = ", ".join(f"{k} {v:.2f} ms" for k, v in out.latency_ms.items())
                print(f"trial {i} seed {seed}: {out.outcome}" + (f" ({lat})" if lat else ""), flush=True)
                if not out.survived:
                    _report_stuck(rig, out, log_dir, wait=not args.no_wait)
                    return 1
                fault.settle(out)
            print(f"{args.trials} trials survived")
            survived = True
            return 0
        finally:
            factory.stop_all()
            if survived:  # nothing to look at: the logs go (a stuck run's are printed and kept)
                shutil.rmtree(log_dir, ignore_errors=True)


def scenario_command(args: argparse.Namespace) -> list[str]:
    """The pytest run that replays a scenario of yours: its trials stop at
    the first that does not survive, whose container is held (until
    Ctrl-C; with --no-wait, not at all)."""
    if args.profile or args.allocator:
        raise SystemExit("--profile and --allocator are for the rig's faults; give a scenario --container-arg")
    if is_node_id(args.fault):
        cmd = [sys.executable, "-m", "pytest", args.fault]
    else:  # a fault of yours by name: the harness's one scenario of it, run as if from this directory
        cmd = [sys.executable, "-m", "pytest", str(named_faults.SCENARIO), f"--named-fault={args.fault}"]
        cmd += ["--import-mode=importlib", f"--rootdir={Path.cwd()}", "-c", str(_config_in(Path.cwd()))]
    cmd += ["-p", "no:cacheprovider", "--seed", str(args.seed)]
    cmd += ["--trial-seed", str(args.trial_seed)] if args.trial_seed is not None else ["--trials", str(args.trials)]
    cmd += ["--hold-failed", "0" if args.no_wait else "inf"]
    cmd += [f"--container-arg={a}" for a in args.container_arg]
    if args.container_exe:
        cmd += ["--container-exe", args.container_exe]
    return cmd


#: pytest's configuration files, in the order it looks for them in a directory
PYTEST_CONFIGS = ("pytest.ini", ".pytest.ini", "pyproject.toml", "tox.ini", "setup.cfg")


def _config_in(directory: Path) -> Path:
    """The pytest configuration of ``directory`` (your project's), else
    none (/dev/null): never the one of the harness's own scenario file,
    which lies in cloneguard's checkout."""
    found = (directory / name for name in PYTEST_CONFIGS)
    return next((p for p in found if p.is_file()), Path(os.devnull))


def run_scenario(args: argparse.Namespace) -> int:
    """pytest's exit status. Ctrl-C is pytest's to handle (it stops a held
    container and writes the report): this process ignores it meanwhile,
    and the child starts with the default action, which Python turns into
    its KeyboardInterrupt."""
    cmd = scenario_command(args)
    print("$ " + " ".join(cmd), flush=True)
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        child = subprocess.Popen(cmd, preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
        return child.wait()
    finally:
        signal.signal(signal.SIGINT, previous)


def _report_stuck(rig: Rig, out: Outcome, log_dir: Path, *, wait: bool) -> None:
    print(f"\n{out.outcome.upper()}: {out.details.get('why', '')}")
    if out.diagnosis is not None:
        stacks = log_dir / "stacks.txt"
        stacks.write_text(out.diagnosis.stacks_text)
        print(f"diagnosis: {out.diagnosis.summary()}")
        print(f"all stacks: {stacks}")
    print(f"container log: {rig.proc.log_path}")
    if out.outcome == TrialOutcome.HUNG and rig.proc.alive():
        if not wait:
            print(f"\nThe container (pid {rig.proc.pid}) is still stuck; stopping it now (--no-wait).")
            return
        kids = sorted(rig.client.nodes_by_pid())
        print(f"\nThe container is still stuck: pid {rig.proc.pid} (node processes {kids}).")
        print(f"Attach a debugger:  gdb -p {rig.proc.pid}    then: thread apply all bt")
        print("Python stacks:      gdb -p PID -batch -ex 'py-bt'   (with CPython's gdb extension)")
        print("Press Ctrl-C to stop it and clean up.", flush=True)
        try:
            signal.pause()
        except KeyboardInterrupt:
            pass
