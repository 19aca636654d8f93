"""``python -m harness reproduce FAULT``: replay a fault until it does not
survive, then stop right there with the container still running, print the
diagnosis, and say how to attach a debugger.

    python -m harness reproduce malloc-kill --allocator glibc --seed 7 --trials 200
    python -m harness reproduce segfault-gil-held --profile shared --trial-seed 123456
"""
from __future__ import annotations

import os
import random
import signal
import tempfile
from pathlib import Path

from faults import trials
from harness import domains
from harness.factory import ContainerFactory
from harness.process import ros_environment
from harness.rig import PROFILES, Rig

ALLOCATOR_ARGS = trials.MALLOC_ALLOCATORS
FAULTS = sorted([*trials.CALLBACK_FAULTS, "sigkill-outside", "die-holding-robust-mutex", "malloc-kill"])


def _trial_fn(fault: str, rig: Rig):
    """trial(seed, index) -> Outcome for ``fault`` on ``rig``."""
    if fault in trials.CALLBACK_FAULTS:
        return lambda seed, i: trials.callback_fault(rig, fault, seed, i), rig.settle
    if fault == "sigkill-outside":
        return lambda seed, i: trials.outside_sigkill(rig, seed, i), rig.settle
    if fault == "die-holding-robust-mutex":
        return lambda seed, i: trials.die_holding_lock(rig, seed, i), rig.settle
    malloc = trials.MallocKill(rig)
    return malloc.trial, malloc.settle


def add_parser(subparsers) -> None:
    p = subparsers.add_parser(
        "reproduce", help="replay a fault until it does not survive, then stop there",
        description=__doc__.split("\n\n")[0],
    )
    p.add_argument("fault", choices=FAULTS)
    p.add_argument("--profile", choices=sorted(PROFILES), default="per-node")
    p.add_argument("--allocator", choices=sorted(ALLOCATOR_ARGS), default="glibc",
                   help="for malloc-kill (default: glibc)")
    p.add_argument("--seed", type=int, default=1, help="base seed; each trial's seed is drawn from it")
    p.add_argument("--trial-seed", type=int, default=None, help="run every trial with this one seed")
    p.add_argument("--trials", type=int, default=100)
    p.add_argument("--no-wait", action="store_true",
                   help="do not wait for Ctrl-C before stopping the stuck container")
    p.set_defaults(func=run)


def run(args) -> int:
    for key, value in ros_environment(0).items():
        if key != "ROS_DOMAIN_ID":
            os.environ[key] = value
    os.environ.pop("ROS_AUTOMATIC_DISCOVERY_RANGE", None)
    log_dir = Path(tempfile.mkdtemp(prefix="cloneguard-reproduce-"))
    rng = random.Random(args.seed)
    with domains.lease() as lease:
        factory = ContainerFactory(lease.domain_id, log_dir)
        try:
            rig = Rig(factory, args.profile, extra_args=ALLOCATOR_ARGS[args.allocator])
            trial, settle = _trial_fn(args.fault, rig)
            for i in range(args.trials):
                seed = args.trial_seed if args.trial_seed is not None else rng.getrandbits(31)
                out = trial(seed, i)
                lat = ", ".join(f"{k} {v:.2f} ms" for k, v in out.latency_ms.items())
                print(f"trial {i} seed {seed}: {out.outcome}" + (f" ({lat})" if lat else ""), flush=True)
                if out.outcome != "survived":
                    _report_stuck(rig, out, log_dir, wait=not args.no_wait)
                    return 1
                settle(out)
            print(f"{args.trials} trials survived")
            return 0
        finally:
            factory.stop_all()


def _report_stuck(rig: Rig, out, log_dir: Path, *, wait: bool) -> None:
    print(f"\n{out.outcome.upper()}: {out.details.get('why', '')}")
    if out.diagnosis is not None:
        stacks = log_dir / "stacks.txt"
        stacks.write_text(out.diagnosis.stacks_text)
        print(f"diagnosis: {out.diagnosis.summary()}")
        print(f"all stacks: {stacks}")
    print(f"container log: {rig.proc.log_path}")
    if out.outcome == "hung" and rig.proc.alive():
        kids = sorted(rig.nodes_by_pid())
        print(f"\nThe container is still stuck: pid {rig.proc.pid} (node processes {kids}).")
        print(f"Attach a debugger:  gdb -p {rig.proc.pid}    then: thread apply all bt")
        print("Python stacks:      gdb -p PID -batch -ex 'py-bt'   (with CPython's gdb extension)")
        if wait:
            print("Press Ctrl-C to stop it and clean up.", flush=True)
            try:
                signal.pause()
            except KeyboardInterrupt:
                pass
