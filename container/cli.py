"""``component_container``: the one executable, in every mode.

    component_container                                # single-threaded executor
    component_container --use_multi_threaded_executor  # multi-threaded executor
    component_container --isolated                     # a clone(CLONE_VM) child per node

ROS arguments (``--ros-args -r __node:=name -r __ns:=/ns ...``) apply to the
container's own node, named ``ComponentManager`` by default.
"""

from __future__ import annotations

import argparse
import faulthandler
import os
import resource
import signal
import sys
import threading
import traceback
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, NoReturn

# OpenBLAS (under numpy, under rclpy's messages) starts a process-wide thread
# pool lazily; started from inside a node's clone child, those threads would
# belong to that child and keep it from ever exiting. One thread: no pool.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import rclpy  # noqa: E402
from rclpy.context import Context
from rclpy.executors import MultiThreadedExecutor
from rclpy.node import Node
from rclpy.signals import SignalHandlerOptions
from rclpy.utilities import remove_ros_args

from . import allocator, diagnostics, memory_budget, seams
from .executors import NodesMultiThreadedExecutor, NodesSingleThreadedExecutor, NodeWork
from .hosting import ThreadHost
from .isolated import profiles
from .isolated.node_watchdog import NodeWatchdog
from .manager import ComponentManager
from .restart import DEFAULT_LIMIT as DEFAULT_RESTART_LIMIT
from .restart import POLICIES
from .stop_signals import StopSignals
from .watchdog import ClockFactory, MonotonicClock, Watchdog, bound_shutdown

if TYPE_CHECKING:
    from rclpy.impl.rcutils_logger import RcutilsLogger

    from .isolated.host import IsolatedHost
    from .isolated.memory_watch import MemoryLimit

DEFAULT_NODE_NAME = "ComponentManager"
# Threads serving LoadNode/UnloadNode/ListNodes (and the watchdog, restarts):
# a load waiting for its node takes one for up to ComponentManager.CONSTRUCT_WAIT_S.
SERVICE_THREADS = 8
# How long stopping waits for requests in flight to be answered (an unload
# may be stopping its node; a load waiting for its node is answered at once).
ANSWER_WAIT_S = 5.0
WATCHDOG_MAX_S = 86400.0

# Mitigations that can be switched off, to measure what each one buys.
MITIGATION_SWITCHES = {
    "--no-gil-repair": "for measurement, do not release the GIL a dead child held",
    "--no-condvar-repair": "for measurement, do not repair the GIL's condition variables "
    "after a child died waiting on them",
    "--no-interp-repair": "for measurement, do not mend what a child that died holding the "
    "GIL may have left half-done in the interpreter (objects it was "
    "changing, GC links, free lists)",
    "--no-crash-report": "no native/Python stack report from a child that crashes",
    "--shared-arenas": "under glibc malloc, let threads and node processes share malloc "
    "arenas as glibc does by default (8 per core); needs --no-alloc-guard",
    "--no-alloc-guard": "for measurement, no allocator guard: blocks are freed into "
    "whichever node's arena they came from, and a node process "
    "killed inside malloc can leave its arena locked for others",
    "--no-python-pools": "for measurement, Python objects from CPython's own allocator "
    "(pymalloc), shared by every node process, instead of the "
    "guard's pools of each process",
    "--no-python-locks": "for measurement, CPython's own lock types (no holder recorded): a "
    "Python lock whose holder's process died stays held",
    "--no-mutex-repair": "for measurement, do not release a pthread mutex whose owner's node "
    "process died (nor report a task blocked on one)",
    "--no-container-gc": "for measurement, let CPython collect garbage on whichever "
    "thread allocates, node processes included, instead of only "
    "on a thread of the container",
}


class _Parser(argparse.ArgumentParser):
    def error(self, message: str) -> NoReturn:
        """One line, exit status 2 (argparse would add the usage)."""
        self.exit(2, f"{self.prog}: error: {message} (see --help)\n")


def _watchdog_seconds(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number of seconds: {text!r}") from None
    if not (0.0 <= value <= WATCHDOG_MAX_S):  # also refuses nan and inf
        raise argparse.ArgumentTypeError(f"must be 0 (off) to {WATCHDOG_MAX_S:g} seconds, got {text!r}")
    return value


def _memory_size(text: str) -> int:
    try:
        return memory_budget.parse_size(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def _restart_limit(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a whole number: {text!r}") from None
    if not 1 <= value <= 1000:
        raise argparse.ArgumentTypeError(f"must be 1 to 1000 restarts, got {text!r}")
    return value


#: How often node processes' participants re-announce themselves, in the
#: per-node profile (bench.scale: at 48 nodes, 100 ms for every participant
#: cost 67% of a core idle, 3 s for the nodes' 12%).
NODE_ANNOUNCEMENT_S = 3.0


def _announcement_seconds(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number of seconds: {text!r}") from None
    if not (value == 0 or 0.01 <= value <= 3600):
        raise argparse.ArgumentTypeError(f"must be 0 (the profile's) or 0.01 to 3600 s, got {text!r}")
    return value


def _profile_rule(text: str) -> profiles.ProfileRule:
    try:
        return profiles.parse_rule(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


class _IsolatedOptions:
    """The options that mean something only with --isolated: the one way
    to add them, so that each is refused without it."""

    def __init__(self, parser: argparse.ArgumentParser) -> None:
        self._group = parser.add_argument_group("isolated mode (each needs --isolated)")
        self.flags: set[str] = set()

    def add_argument(self, *args: str, **kwargs: Any) -> argparse.Action:
        action = self._group.add_argument(*args, **kwargs)
        self.flags.update(action.option_strings)
        return action


def parse_args(argv: list[str]) -> argparse.Namespace:
    """The container's own options; a refused one or combination is one
    line on stderr and exit status 2."""
    parser = _Parser(
        prog="component_container",
        allow_abbrev=False,  # an isolated-only flag must be seen for what it is
        description="ROS 2 component container (rclpy) with optional per-node clone(CLONE_VM) process isolation.",
    )
    _add_options(parser)
    isolated = _IsolatedOptions(parser)
    _add_isolated_options(isolated)
    opts = parser.parse_args(argv)
    given = {arg.split("=", 1)[0] for arg in argv if arg.startswith("--")}
    _check_isolated(parser, opts, given, isolated.flags)
    _choose_allocator(parser, opts, given)
    _check_combinations(parser, opts, given)
    return opts


def _add_options(parser: argparse.ArgumentParser) -> None:
    """The options of every mode."""
    parser.add_argument(
        "--use_multi_threaded_executor",
        "--use-multi-threaded-executor",
        action="store_true",
        help="spin the container's nodes on a multi-threaded executor",
    )
    parser.add_argument(
        "--isolated",
        action="store_true",
        help="run each loaded node's executor in its own clone(CLONE_VM) process",
    )
    parser.add_argument(
        "--allocator",
        choices=allocator.ALLOCATORS,
        default=None,
        help="the malloc the container runs on; jemalloc re-executes it with Debian's libjemalloc2 "
        "preloaded (default: jemalloc in isolated mode wherever libjemalloc2 is installed, since only "
        "there can node heaps be under protection keys; glibc otherwise and in thread mode)",
    )
    parser.add_argument(
        "--jemalloc",
        dest="allocator",
        action="store_const",
        const="jemalloc",
        help="--allocator jemalloc",
    )
    parser.add_argument(
        "--watchdog",
        type=_watchdog_seconds,
        default=None,
        metavar="SECONDS",
        help="exit with every thread's stack when the container's executor makes no "
        "progress for SECONDS (default: 10 in isolated mode, off otherwise; 0: off)",
    )
    parser.add_argument(
        "--shutdown-timeout",
        type=_watchdog_seconds,
        default=None,
        metavar="SECONDS",
        help="exit with every thread's stack (status 1) if stopping takes longer than SECONDS "
        "(default: the --watchdog timeout; 0: no bound)",
    )


def _add_isolated_options(isolated: _IsolatedOptions) -> None:
    """The options that need --isolated."""
    isolated.add_argument(
        "--profile",
        choices=profiles.PROFILES,
        default=profiles.DEFAULT,
        help="where nodes are built: each in its own process either way, on the container's rclpy Context "
        "and DDS participant ('shared') or on one of its own ('per-node') (default: %(default)s)",
    )
    isolated.add_argument(
        "--profile-for",
        type=_profile_rule,
        action="append",
        default=[],
        metavar="PATTERN=PROFILE",
        help="build the nodes whose requested full name (/ns/name) or plugin (pkg::Class) matches "
        "PATTERN (fnmatch) in PROFILE instead of --profile's; repeat it, the first match wins "
        "(a load's own cloneguard.profile wins over all)",
    )
    isolated.add_argument(
        "--no-warm-spare",
        action="store_true",
        help="per-node profile: do not keep the next node's process, with its DDS "
        "participant, made ahead of the LoadNode (it is made during each load instead)",
    )
    isolated.add_argument(
        "--node-announcement",
        type=_announcement_seconds,
        default=None,
        metavar="SECONDS",
        help="per-node profile: node processes' DDS participants re-announce themselves every "
        f"SECONDS; the container's own participant keeps the Fast DDS profile's period, so that "
        f"tools find the container as fast as the profile says (default: {NODE_ANNOUNCEMENT_S:g}, "
        "Fast DDS's own default; 0: the profile's for every participant)",
    )
    isolated.add_argument(
        "--cgroups",
        action="store_true",
        help="each node's process in a cgroup of its own (cgroup2, CLONE_INTO_CGROUP); "
        "LoadNode extra argument 'cloneguard.cpu_quota' (CPUs) sets a CPU quota",
    )
    isolated.add_argument(
        "--restart-policy",
        choices=POLICIES,
        default="never",
        help="'on-crash' loads a node whose process died again, after 0.5 s doubling to "
        "30 s (reset once it stayed up 60 s) (default: %(default)s)",
    )
    isolated.add_argument(
        "--restart-limit",
        type=_restart_limit,
        default=DEFAULT_RESTART_LIMIT,
        metavar="N",
        help="with --restart-policy on-crash: a node that died N restarts in a row, none of "
        "them up 60 s, is not restarted again (each crash leaves its process's objects in "
        "memory) (default: %(default)s)",
    )
    isolated.add_argument(
        "--node-memory-limit",
        type=_memory_size,
        default=0,
        metavar="SIZE",
        help="each node process's memory budget (512M, 2G): one that would go over it ends "
        "itself just before, alone, its CRASHED saying so; LoadNode extra argument "
        f"'{memory_budget.MEMORY_LIMIT}' gives one node its own (needs the allocator guard) (default: none)",
    )
    isolated.add_argument(
        "--memory-margin",
        type=_memory_size,
        default=None,
        metavar="SIZE",
        help="the memory watch ends the node process that uses the most once the container's "
        "memory is within SIZE of what it may use (its memory cgroup's limit, else the machine's "
        "memory), before the kernel's OOM killer would end the whole container; LoadNode extra "
        f"argument '{memory_budget.OOM_SCORE_ADJ}' (-1000 to 1000) weighs one node as oom_score_adj does "
        "(default: 2%% of the limit, at least 64M)",
    )
    isolated.add_argument(
        "--no-memory-watch",
        action="store_true",
        help="no memory watch (see --memory-margin): the kernel's OOM killer ends the whole container",
    )
    isolated.add_argument(
        "--node-watchdog",
        type=_watchdog_seconds,
        default=0.0,
        metavar="SECONDS",
        help="abort (SIGABRT, with its stacks) a node whose callback has run longer than "
        "SECONDS and report it CRASHED; the other nodes go on (default: 0, off)",
    )
    isolated.add_argument(
        "--jemalloc-arenas",
        choices=("own", "auto"),
        default="own",
        help="with jemalloc and --no-alloc-guard: 'own' binds each node's process to an "
        "arena of its own, 'auto' leaves the choice to jemalloc (the guard always gives "
        "each its own) (default: %(default)s)",
    )
    isolated.add_argument(
        "--pkeys",
        action="store_const",
        const=True,
        default=None,
        help="each node process's native heap under a memory protection key of its own, writable "
        "by it and the container only, so that a stray write into another node's heap kills the "
        "writer before it lands; needs jemalloc and the allocator guard (default: on wherever "
        "they can be: jemalloc, the guard, and a CPU and kernel with keys; asked for "
        "explicitly, refused where they cannot be)",
    )
    isolated.add_argument(
        "--no-pkeys",
        dest="pkeys",
        action="store_const",
        const=False,
        help="no protection keys over node heaps, even where they could be (to measure without)",
    )
    isolated.add_argument(
        "--core-dumps",
        type=Path,
        default=None,
        metavar="DIR",
        help="write the core dump of a node process that catches a fatal signal into DIR as "
        "core.<node>.<pid> (with gdb, while it waits in its crash handler); each holds the whole "
        "shared address space, every node's memory and the container's (default: none)",
    )
    for flag, what in MITIGATION_SWITCHES.items():
        isolated.add_argument(flag, action="store_true", help=what)


def _check_isolated(
    parser: argparse.ArgumentParser, opts: argparse.Namespace, given: set[str], isolated_flags: set[str]
) -> None:
    """Isolated-only options refused without --isolated; the node announcement's
    period, which depends on the mode."""
    if not opts.isolated:
        for flag in sorted(isolated_flags & given):
            parser.error(f"{flag} needs --isolated")
    if opts.node_announcement is None:
        # Whatever the container's profile: a rule or a LoadNode may give a
        # node a participant of its own (the only participants it sets).
        opts.node_announcement = NODE_ANNOUNCEMENT_S if opts.isolated else 0.0


def _choose_allocator(parser: argparse.ArgumentParser, opts: argparse.Namespace, given: set[str]) -> None:
    """opts.allocator as asked, else the mode's default; opts.jemalloc says
    which, and opts.allocator_why why an isolated container is on glibc by
    default (None where it is not)."""
    if "--jemalloc" in given and "--allocator" in given:
        parser.error("--jemalloc is --allocator jemalloc: one or the other")
    opts.allocator_why = None
    if opts.allocator is None:
        if not opts.isolated:
            opts.allocator = "glibc"
        elif allocator.jemalloc_path() is None:
            opts.allocator = "glibc"
            opts.allocator_why = f"{allocator.JEMALLOC_MISSING}, so node heaps are without protection keys"
        else:
            opts.allocator = "jemalloc"
    opts.jemalloc = opts.allocator == "jemalloc"


def _check_combinations(parser: argparse.ArgumentParser, opts: argparse.Namespace, given: set[str]) -> None:
    """Combinations refused: an option that needs another, or one its other contradicts."""
    if opts.node_memory_limit and opts.no_alloc_guard:
        parser.error(
            "--node-memory-limit needs the allocator guard, which counts each node's memory: not --no-alloc-guard"
        )
    if opts.memory_margin is not None and (opts.no_memory_watch or opts.no_alloc_guard):
        parser.error(
            "--memory-margin needs the memory watch, which weighs nodes by the allocator guard's "
            "count: not --no-memory-watch, nor --no-alloc-guard"
        )
    if "--restart-limit" in given and opts.restart_policy != "on-crash":
        parser.error("--restart-limit needs --restart-policy on-crash")
    if "--jemalloc-arenas" in given and not (opts.jemalloc and opts.no_alloc_guard):
        parser.error(
            "--jemalloc-arenas needs jemalloc and --no-alloc-guard (the allocator guard "
            "gives every node process an arena of its own)"
        )
    if "--pkeys" in given and "--no-pkeys" in given:
        parser.error("--pkeys and --no-pkeys: one or the other")
    if opts.pkeys and not (opts.jemalloc and not opts.no_alloc_guard):
        parser.error(
            "--pkeys needs jemalloc and the allocator guard (the keys tag the ranges the "
            "guard's jemalloc arenas carve each node's heap from)"
        )
    if opts.core_dumps is not None and opts.no_crash_report:
        parser.error("--core-dumps needs the crash report (the node waits for its dump in its crash handler)")
    if opts.no_python_pools and opts.no_alloc_guard:
        parser.error("--no-python-pools means nothing with --no-alloc-guard (the pools are the guard's)")
    if opts.shared_arenas and (opts.jemalloc or not opts.no_alloc_guard):
        parser.error(
            "--shared-arenas needs --allocator glibc and --no-alloc-guard (the allocator guard "
            "gives every node process an arena of its own)"
        )


def _ros_init(argv: list[str]) -> None:
    """rclpy.init, with bad ROS arguments (an invalid remap, a missing
    parameter file, bytes that are not UTF-8 ...) said in one line."""
    try:
        rclpy.init(args=argv, signal_handler_options=SignalHandlerOptions.NO)
    except Exception as exc:
        first = (str(exc).strip().splitlines() or [type(exc).__name__])[0]
        raise SystemExit(f"component_container: invalid ROS arguments: {first}") from None


def _raise_open_file_limit() -> tuple[int, int] | None:
    """Isolated mode: the soft RLIMIT_NOFILE up to the hard one; (old, new),
    or None if it was there already. Node processes share the container's
    file descriptors, and a per-node node that crashes leaves its
    participant's sockets open with the rest of it (~9 fds): at a soft limit
    of 1024, a common default, the container could build no node after
    ~110 crashes."""
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    # Linux caps the limit at fs.nr_open, whatever "unlimited" says.
    top = hard if hard != resource.RLIM_INFINITY else int(open("/proc/sys/fs/nr_open").read())
    if soft == resource.RLIM_INFINITY or soft >= top:
        return None
    try:
        resource.setrlimit(resource.RLIMIT_NOFILE, (top, hard))
    except (ValueError, OSError):
        return None
    return soft, top


def _announce_nodes_every(seconds: float, logger: RcutilsLogger) -> None:
    """Node processes' participants (made after the container's own) at
    their own announcement period (isolated/dds_defaults.cpp)."""
    from .isolated.dds_defaults import DdsDefaultsUnavailable, announce_nodes_every

    try:
        before, after = announce_nodes_every(seconds)
    except DdsDefaultsUnavailable as exc:
        raise SystemExit(f"component_container: --node-announcement is unavailable here: {exc}") from None
    logger.info(f"node processes' participants announce every {after:g} s (the container's own: {before:g} s)")


def _heap_keys_wanted(opts: argparse.Namespace) -> bool:
    """Ask the allocator guard for protection keys as it starts? Asked for
    (--pkeys), or by default wherever they could be (jemalloc and the
    guard; the guard finds out whether the CPU and kernel have them)."""
    if not opts.isolated or opts.pkeys is False:
        return False
    return bool(opts.pkeys) or (opts.jemalloc and not opts.no_alloc_guard)


def _check_heap_keys(opts: argparse.Namespace, logger: RcutilsLogger) -> None:
    """Say in the log whether node heaps are under protection keys, and
    why not; refuse an explicit --pkeys that cannot be had, and keys the
    guard holds where a fact they rest on does not hold (pkeys.c)."""
    from .isolated import pkeys

    if not _heap_keys_wanted(opts):
        if opts.pkeys is False:
            why = "--no-pkeys"
        elif opts.no_alloc_guard:
            why = "--no-alloc-guard: the keys tag the ranges the guard's arenas carve node heaps from"
        elif opts.allocator_why:  # the default fell back to glibc: said louder than a choice
            logger.warning(f"glibc malloc: {opts.allocator_why}")
            return
        else:
            why = pkeys.cpu_lacks_keys() or pkeys.NEEDS_JEMALLOC
        logger.info(f"memory protection keys over node heaps: off ({why})")
        return
    keys = pkeys.heap_keys()
    if isinstance(keys, str) and not opts.pkeys:  # the default, where the CPU or kernel has none
        logger.info(f"memory protection keys over node heaps: off ({pkeys.cpu_lacks_keys() or keys})")
        return
    broken = pkeys.heap_keys_unavailable()
    if broken is not None:
        if opts.pkeys:
            raise SystemExit(f"component_container: --pkeys is unavailable here: {broken}")
        raise SystemExit(
            "component_container: protection keys over node heaps (the default on jemalloc) cannot "
            f"be had here: {broken}; --no-pkeys runs without them"
        )
    logger.info(pkeys.heap_keys_describe())


def _fastdds_intraprocess_off(logger: RcutilsLogger) -> None:
    """No Fast DDS participant thread delivers into another participant's
    readers by calling into them (docs/fastdds.md: a node process killed in
    there leaves the other's locks held)."""
    from .isolated.dds_defaults import DdsDefaultsUnavailable, intraprocess_off

    try:
        was = intraprocess_off()
    except DdsDefaultsUnavailable as exc:
        raise SystemExit(f"component_container: --isolated is unavailable here: {exc}") from None
    if was != "OFF":
        logger.warning(
            f"Fast DDS intraprocess delivery turned off (the profile had {was}): in an isolated container "
            "no DDS participant's thread may run inside another one's readers (docs/fastdds.md)"
        )


def _watch_clock(opts: argparse.Namespace) -> ClockFactory:
    """What the watchdog and the shutdown bound read time on: in isolated
    mode the clone core's clock, which stands still while a core dump is
    written (a node that crashed holding the GIL waits for it with the GIL)."""
    if not opts.isolated:
        return MonotonicClock
    from .isolated.watch_clock import DumpPausedClock

    return DumpPausedClock


def _make_host(
    opts: argparse.Namespace,
    argv: list[str],
    executor: NodeWork,
    context: Context,
    logger: RcutilsLogger,
) -> ThreadHost | IsolatedHost:
    if not opts.isolated:
        return ThreadHost(executor, context, logger)
    # Imported here: thread mode must work where the C core cannot (not
    # built on this platform: setup.py); the self-check says so.
    from .isolated.assumptions import IsolationUnavailable, core_module

    try:
        _, core = core_module()  # the modules below import it
    except IsolationUnavailable as exc:
        raise SystemExit(f"component_container: --isolated is unavailable here: {exc}") from None
    # A fatal signal in the container itself: its native stack first, then
    # faulthandler's Python stacks (enabled by main) as before.
    core.cg_container_crash_report()
    if opts.core_dumps is not None:
        from .isolated import core_dumps

        why = core_dumps.unavailable(opts.core_dumps)
        if why is not None:
            raise SystemExit(f"component_container: --core-dumps {opts.core_dumps}: {why}")
        opts.core_dumps = opts.core_dumps.resolve()
        logger.warning(
            f"core dumps of node processes that crash go to {opts.core_dumps}: each holds "
            "the whole shared address space (every node's memory and the container's)"
        )
    _check_heap_keys(opts, logger)
    from .isolated.cgroups import CgroupsUnavailable, NodeCgroups
    from .isolated.core import Mitigations
    from .isolated.host import IsolatedHost

    mitigations = Mitigations(
        gil_repair=not opts.no_gil_repair,
        condvar_repair=not opts.no_condvar_repair,
        interp_repair=not opts.no_interp_repair,
        crash_report=not opts.no_crash_report,
        jemalloc_arena=opts.jemalloc_arenas,
        alloc_guard=not opts.no_alloc_guard,
        container_gc=not opts.no_container_gc,
        mutex_repair=False if opts.no_mutex_repair else None,
    )
    try:
        cgroups = NodeCgroups() if opts.cgroups else None
    except CgroupsUnavailable as exc:
        raise SystemExit(f"component_container: --cgroups is unavailable here: {exc}") from None
    for stale in cgroups.reclaimed if cgroups is not None else ():
        logger.warning(f"removed the empty cgroup {stale}, left by a dead container that had this pid")
    try:
        return IsolatedHost(
            context,
            profile=opts.profile,
            profile_rules=opts.profile_for,
            logger=logger,
            cgroups=cgroups,
            mitigations=mitigations,
            warm_spare=not opts.no_warm_spare,
            container_argv=argv,
            core_dumps=opts.core_dumps,
            stop_signal=opts.stop_signal,
            node_memory_limit=opts.node_memory_limit,
            memory_watch=_memory_watch(opts, logger),
        )
    except IsolationUnavailable as exc:
        if cgroups is not None:
            cgroups.close()
        raise SystemExit(f"component_container: --isolated is unavailable here: {exc}") from None


def _memory_watch(opts: argparse.Namespace, logger: RcutilsLogger) -> tuple[MemoryLimit, int] | None:
    """(what the container may use, the margin) for the memory watch, or
    None: off, or without the allocator guard to weigh nodes."""
    if opts.no_memory_watch or opts.no_alloc_guard:
        return None
    from .isolated import memory_watch

    limit = memory_watch.find()
    margin = limit.margin(opts.memory_margin)
    if margin >= limit.limit:
        raise SystemExit(
            f"component_container: --memory-margin {memory_budget.describe(margin)} leaves nothing of "
            f"the {memory_budget.describe(limit.limit)} the container may use ({limit.where})"
        )
    logger.info(
        f"memory watch: the container may use {memory_budget.describe(limit.limit)} ({limit.where}); "
        f"from {memory_budget.describe(limit.limit - margin)} on it ends the node process that uses the most"
    )
    return limit, margin


@dataclass
class _Container:
    """A built container: its node, executors, host and manager, and what
    watches them; ``serve`` runs it until a stop signal, ``stop`` ends it."""

    opts: argparse.Namespace
    stop_signals: StopSignals
    context: Context
    node: Node
    executor: NodeWork
    services: MultiThreadedExecutor
    host: Any
    manager: ComponentManager
    watchdog_s: float
    watchdog: Watchdog | None
    node_watchdog: NodeWatchdog | None
    failure: list[BaseException] = field(default_factory=list)
    threads: list[threading.Thread] = field(default_factory=list)
    services_stopping: threading.Event = field(default_factory=threading.Event)


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv if argv is None else argv)
    opts, raised_fd_limit = _prepare_process(argv)
    container = _build(opts, argv, raised_fd_limit)
    signum = _serve(container)
    return _stop(container, signum)


def _prepare_process(argv: list[str]) -> tuple[argparse.Namespace, tuple[int, int] | None]:
    """The options, and what the process needs before its second thread:
    the preloaded allocator (re-executing if it is not), glibc's arenas, the
    open-file limit (raised: (old, new), or None), faulthandler."""
    try:
        plain = remove_ros_args(argv)[1:]
    except Exception as exc:
        raise SystemExit(f"component_container: invalid ROS arguments: {exc}") from None
    opts = parse_args(plain)
    try:  # the test rig's stop points (seams.py), checked before anything starts
        opts.stop_signal = seams.stop_signal() if opts.isolated else 0
    except ValueError as exc:
        raise SystemExit(f"component_container: {exc}") from None
    guard = opts.isolated and not opts.no_alloc_guard
    python_locks = opts.isolated and not opts.no_python_locks
    if guard or opts.jemalloc or python_locks:
        try:
            # Returns only once what is asked for is in use (else re-executes).
            allocator.ensure_preloaded(
                argv,
                guard=guard,
                jemalloc=opts.jemalloc,
                python_pools=not opts.no_python_pools,
                python_locks=python_locks,
                pkeys=_heap_keys_wanted(opts),
            )
        except allocator.AllocatorUnavailable as exc:
            raise SystemExit(f"component_container: {exc}") from None
    if opts.isolated and not opts.shared_arenas:
        allocator.glibc_arena_per_task()  # before a second thread exists
    raised_fd_limit = _raise_open_file_limit() if opts.isolated else None
    # If the container process itself dies of a fault, the log says where:
    # every thread's Python stack (its children have crash reports of their
    # own; they start with no handler).
    faulthandler.enable(file=sys.stderr, all_threads=True)
    return opts, raised_fd_limit


def _build(opts: argparse.Namespace, argv: list[str], raised_fd_limit: tuple[int, int] | None) -> _Container:
    stop_signals = StopSignals()
    _ros_init(argv)
    context = rclpy.get_default_context()
    node = Node(DEFAULT_NODE_NAME, context=context)
    if opts.isolated:  # the container's own participant (its Context's) exists now
        _fastdds_intraprocess_off(node.get_logger())
    if opts.node_announcement > 0:
        _announce_nodes_every(opts.node_announcement, node.get_logger())
    if raised_fd_limit:
        node.get_logger().info(
            f"open-file limit raised from {raised_fd_limit[0]} to {raised_fd_limit[1]}: "
            "node processes share this process's file descriptors"
        )
    try:
        diagnostics_period = diagnostics.declared_period(node)
    except ValueError as exc:
        node.destroy_node()
        rclpy.try_shutdown()
        raise SystemExit(f"component_container: {exc}") from None
    # Thread mode's nodes spin on this executor (as upstream's containers);
    # the container's own services spin on one of their own, so that no
    # node's callback, nor a LoadNode waiting for a constructor, can keep
    # them from answering.
    executor = (
        NodesMultiThreadedExecutor(context=context)
        if opts.use_multi_threaded_executor
        else NodesSingleThreadedExecutor(context=context)
    )
    services = MultiThreadedExecutor(num_threads=SERVICE_THREADS, context=context)
    try:
        host = _make_host(opts, argv, executor, context, node.get_logger())
    except SystemExit:
        node.destroy_node()
        rclpy.try_shutdown()
        raise
    manager = ComponentManager(
        node,
        host,
        restart_limit=opts.restart_limit if opts.restart_policy == "on-crash" else None,
        diagnostics_period_s=diagnostics_period,
    )
    services.add_node(node)
    watchdog_s = opts.watchdog if opts.watchdog is not None else (10.0 if opts.isolated else 0.0)
    watchdog = None
    if watchdog_s > 0:
        # In isolated mode each tick also reads the progress board, so a lock
        # a dead child left on it is found and repaired even when idle.
        on_tick = host.board.snapshot if opts.isolated else None  # type: ignore[union-attr]  # an IsolatedHost
        watchdog = Watchdog(node, watchdog_s, executors=[executor], on_tick=on_tick, clock=_watch_clock(opts))
    # --node-watchdog needs --isolated (parse_args): the host is an IsolatedHost.
    node_watchdog = NodeWatchdog(node, host, opts.node_watchdog) if opts.node_watchdog > 0 else None  # type: ignore[arg-type]
    return _Container(
        opts, stop_signals, context, node, executor, services, host, manager, watchdog_s, watchdog, node_watchdog
    )


def _serve(c: _Container) -> int:
    """Spin the nodes and the services, each on a thread of its own, until
    a stop signal (or a callback's exception) comes; its number."""
    c.threads = [
        threading.Thread(target=_spin, args=(c.executor, c.stop_signals, c.failure), name="container-executor"),
        threading.Thread(
            target=_serve_services, args=(c.services, c.node, c.services_stopping), name="container-services"
        ),
    ]
    for t in c.threads:
        t.start()
    opts = c.opts
    c.node.get_logger().info(
        f"{c.node.get_fully_qualified_name()} ready "
        f"({'multi' if opts.use_multi_threaded_executor else 'single'}-threaded executor"
        f"{', isolated, profile ' + opts.profile if opts.isolated else ''}, {allocator.describe()})"
    )
    return c.stop_signals.wait()


def _stop(c: _Container, signum: int) -> int:
    """Stop serving first, then stop the nodes, then tear down our own DDS
    side, within the shutdown bound; the exit status."""
    log = c.node.get_logger()
    if c.failure:
        # As with rclcpp: an exception escaping a callback ends the container.
        log.fatal(f"stopping: a callback raised {type(c.failure[0]).__name__}: {c.failure[0]}")
    else:
        log.info(f"stopping ({signal.Signals(signum).name})")
    if c.watchdog is not None:
        c.watchdog.close()
    shutdown_s = c.opts.shutdown_timeout if c.opts.shutdown_timeout is not None else c.watchdog_s
    shutdown_bound = bound_shutdown(shutdown_s, _watch_clock(c.opts)) if shutdown_s > 0 else None
    if c.node_watchdog is not None:
        c.node_watchdog.close()
    c.manager.stopping()  # answer loads still waiting for their node
    unanswered = c.manager.wait_answered(ANSWER_WAIT_S)
    if unanswered:
        log.warning(f"stopping with {unanswered} request(s) unanswered after {ANSWER_WAIT_S:g} s")
    spinner, server = c.threads
    c.services_stopping.set()
    c.services.shutdown()
    server.join()
    c.executor.shutdown()
    spinner.join()
    try:
        c.manager.close()
    except Exception:  # shutdown goes on regardless
        log.error("stopping the nodes failed:\n" + traceback.format_exc())
    c.node.destroy_node()
    rclpy.try_shutdown()
    # Destroying the context destroys its DDS participant now, which unlinks
    # its /dev/shm segments when the SHM transport is on.
    c.context.destroy()
    c.stop_signals.close()
    if shutdown_bound is not None:
        shutdown_bound.close()
    status = 1 if c.failure else 0
    if c.opts.isolated:
        # Objects a dead child left behind (see isolated/host.py) must never
        # be destroyed: the C++ static destructors that exit() runs would do
        # it (Fast DDS destroys every participant it still knows) and block
        # on a condition variable the dead child was waiting on. Everything
        # of ours is already stopped; flush and leave without them.
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(status)
    return status


def _serve_services(services: MultiThreadedExecutor, node: Node, stopping: threading.Event) -> None:
    """The services' executor: its callbacks contain their own failures
    (manager.py); should anything still escape, it is logged and serving
    goes on. Once ``stopping`` is set, nothing is logged: rclpy 7.1's
    shutdown() destroys the executor's guard condition under a spin in
    progress, which then raises InvalidHandle ("destruction was requested";
    seen once in a thread-mode stop under load)."""
    while True:
        try:
            services.spin()
            return  # shut down
        except Exception:
            if stopping.is_set() or not node.context.ok():
                return
            node.get_logger().error("a service callback raised (served on):\n" + traceback.format_exc())


def _spin(executor: NodeWork, stop: StopSignals, failure: list) -> None:
    try:
        executor.spin()
    except BaseException as exc:
        traceback.print_exc()
        failure.append(exc)
    finally:
        stop.post()  # if spin ended on its own (an error), the main thread stops too


if __name__ == "__main__":
    sys.exit(main())
