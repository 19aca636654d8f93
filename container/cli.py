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

# OpenBLAS (under numpy, under rclpy's messages) starts a process-wide thread
# pool lazily; started from inside a node's clone child, those threads would
# belong to that child and keep it from ever exiting. One thread: no pool.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import rclpy  # noqa: E402
from rclpy.executors import MultiThreadedExecutor, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.signals import SignalHandlerOptions
from rclpy.utilities import remove_ros_args

from . import allocator, options
from .hosting import ThreadHost
from .isolated import profiles
from .isolated.node_watchdog import NodeWatchdog
from .manager import ComponentManager
from .restart import POLICIES, RestartPolicy
from .stop_signals import StopSignals
from .watchdog import Watchdog, bound_shutdown

DEFAULT_NODE_NAME = "ComponentManager"
# Threads serving LoadNode/UnloadNode/ListNodes (and the watchdog, restarts):
# a load waiting for its node takes one for up to ComponentManager.CONSTRUCT_WAIT_S.
SERVICE_THREADS = 8
WATCHDOG_MAX_S = 86400.0

# Mitigations that can be switched off, to measure what each one buys.
# Options that mean something only with --isolated (refused without it).
ISOLATED_ONLY = ("--jemalloc-arenas", "--no-gil-repair", "--no-condvar-repair", "--no-crash-report",
                 "--shared-arenas", "--no-alloc-guard", "--cgroups", "--restart-policy", "--profile",
                 "--node-watchdog", "--no-warm-spare")
MITIGATION_SWITCHES = {
    "--no-gil-repair": "for measurement, do not release the GIL a dead child held",
    "--no-condvar-repair": "for measurement, do not repair the GIL's condition variables "
                           "after a child died waiting on them",
    "--no-crash-report": "no native/Python stack report from a child that crashes",
    "--shared-arenas": "under glibc malloc, let threads and node processes share malloc "
                       "arenas as glibc does by default (8 per core); needs --no-alloc-guard",
    "--no-alloc-guard": "for measurement, no allocator guard: blocks are freed into "
                        "whichever node's arena they came from, and a node process "
                        "killed inside malloc can leave its arena locked for others",
}


class _Parser(argparse.ArgumentParser):
    def error(self, message: str):
        """One line, exit status 2 (argparse would add the usage)."""
        self.exit(2, f"{self.prog}: error: {message} (see --help)\n")


def _watchdog_seconds(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number of seconds: {text!r}") from None
    if not (0.0 <= value <= WATCHDOG_MAX_S):     # also refuses nan and inf
        raise argparse.ArgumentTypeError(f"must be 0 (off) to {WATCHDOG_MAX_S:g} seconds, got {text!r}")
    return value


def parse_args(argv: list[str]) -> argparse.Namespace:
    parser = _Parser(
        prog="component_container",
        allow_abbrev=False,           # an isolated-only flag must be seen for what it is
        description="ROS 2 component container (rclpy) with optional per-node "
        "clone(CLONE_VM) process isolation.",
    )
    parser.add_argument(
        "--use_multi_threaded_executor", "--use-multi-threaded-executor",
        action="store_true",
        help="spin the container's nodes on a multi-threaded executor",
    )
    parser.add_argument(
        "--isolated", action="store_true",
        help="run each loaded node's executor in its own clone(CLONE_VM) process",
    )
    parser.add_argument(
        "--jemalloc", action="store_true",
        help="run on jemalloc (re-executes with Debian's libjemalloc2 preloaded)",
    )
    parser.add_argument(
        "--jemalloc-arenas", choices=("own", "auto"), default="own",
        help="isolated mode under jemalloc, with --no-alloc-guard: 'own' binds each node's "
        "process to an arena of its own, 'auto' leaves the choice to jemalloc (the guard "
        "always gives each its own) (default: %(default)s)",
    )
    for flag, what in MITIGATION_SWITCHES.items():
        parser.add_argument(flag, action="store_true", help=f"isolated mode: {what}")
    parser.add_argument(
        "--cgroups", action="store_true",
        help="isolated mode: each node's process in a cgroup of its own (cgroup2, "
        "CLONE_INTO_CGROUP); LoadNode extra argument 'cloneguard.cpu_quota' (CPUs) sets a CPU quota",
    )
    parser.add_argument(
        "--restart-policy", choices=POLICIES, default="never",
        help="isolated mode: 'on-crash' loads a node whose process died again, after "
        "0.5 s doubling to 30 s (reset once it stayed up 60 s) (default: %(default)s)",
    )
    parser.add_argument(
        "--watchdog", type=_watchdog_seconds, default=None, metavar="SECONDS",
        help="exit with every thread's stack when the container's executor makes no "
        "progress for SECONDS (default: 10 in isolated mode, off otherwise; 0: off)",
    )
    parser.add_argument(
        "--shutdown-timeout", type=_watchdog_seconds, default=None, metavar="SECONDS",
        help="exit with every thread's stack (status 1) if stopping takes longer than SECONDS "
        "(default: the --watchdog timeout; 0: no bound)",
    )
    parser.add_argument(
        "--node-watchdog", type=_watchdog_seconds, default=0.0, metavar="SECONDS",
        help="isolated mode: abort (SIGABRT, with its stacks) a node whose callback has run "
        "longer than SECONDS and report it CRASHED; the other nodes go on (default: 0, off)",
    )
    parser.add_argument(
        "--no-warm-spare", action="store_true",
        help="isolated per-node profile: do not keep the next node's process, with its DDS "
        "participant, made ahead of the LoadNode (it is made during each load instead)",
    )
    parser.add_argument(
        "--profile", choices=profiles.PROFILES, default=profiles.DEFAULT,
        help="isolated mode: where nodes are built; 'per-node' gives each child "
        "its own rclpy Context and DDS participant, 'shared' builds them on the "
        "container's (default: %(default)s)",
    )
    opts = parser.parse_args(argv)
    if not opts.isolated:
        given = {arg.split("=", 1)[0] for arg in argv if arg.startswith("--")}
        for flag in ISOLATED_ONLY:
            if flag in given:
                parser.error(f"{flag} needs --isolated")
    return opts


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


def _make_host(opts, executor, context, logger):
    if not opts.isolated:
        return ThreadHost(executor, context)
    # Imported here: thread mode must work where the C core cannot (not
    # built on this platform: setup.py); the self-check says so.
    from .isolated.assumptions import IsolationUnavailable
    from .isolated.cgroups import CgroupsUnavailable, NodeCgroups
    from .isolated.core import Mitigations
    from .isolated.host import IsolatedHost
    mitigations = Mitigations(
        gil_repair=not opts.no_gil_repair,
        condvar_repair=not opts.no_condvar_repair,
        crash_report=not opts.no_crash_report,
        jemalloc_arena=opts.jemalloc_arenas,
        alloc_guard=not opts.no_alloc_guard,
    )
    try:
        cgroups = NodeCgroups() if opts.cgroups else None
    except CgroupsUnavailable as exc:
        raise SystemExit(f"component_container: --cgroups is unavailable here: {exc}") from None
    for stale in cgroups.reclaimed if cgroups is not None else ():
        logger.warning(f"removed the empty cgroup {stale}, left by a dead container that had this pid")
    try:
        return IsolatedHost(context, profile=opts.profile, logger=logger, cgroups=cgroups,
                            mitigations=mitigations, warm_spare=not opts.no_warm_spare)
    except IsolationUnavailable as exc:
        if cgroups is not None:
            cgroups.close()
        raise SystemExit(f"component_container: --isolated is unavailable here: {exc}") from None


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv if argv is None else argv)
    try:
        plain = remove_ros_args(argv)[1:]
    except Exception as exc:
        raise SystemExit(f"component_container: invalid ROS arguments: {exc}") from None
    opts = parse_args(plain)
    guard = opts.isolated and not opts.no_alloc_guard
    if guard and (opts.shared_arenas or opts.jemalloc_arenas != "own"):
        raise SystemExit("component_container: --shared-arenas and --jemalloc-arenas auto "
                         "need --no-alloc-guard (the guard gives every node process an arena "
                         "of its own)")
    if guard or opts.jemalloc:
        try:
            # Returns only once what is asked for is in use (else re-executes).
            allocator.ensure_preloaded(argv, guard=guard, jemalloc=opts.jemalloc)
        except allocator.AllocatorUnavailable as exc:
            raise SystemExit(f"component_container: {exc}") from None
    if opts.isolated and not opts.shared_arenas:
        allocator.glibc_arena_per_task()        # before a second thread exists
    raised_fd_limit = _raise_open_file_limit() if opts.isolated else None
    # If the container process itself dies of a fault, the log says where:
    # every thread's Python stack (its children have crash reports of their
    # own; they start with no handler).
    faulthandler.enable(file=sys.stderr, all_threads=True)
    stop = StopSignals()
    _ros_init(argv)
    options.container_argv = list(argv)
    context = rclpy.get_default_context()
    node = Node(DEFAULT_NODE_NAME, context=context)
    if raised_fd_limit:
        node.get_logger().info(f"open-file limit raised from {raised_fd_limit[0]} to {raised_fd_limit[1]}: "
                               "node processes share this process's file descriptors")
    # Thread mode's nodes spin on this executor (as upstream's containers);
    # the container's own services spin on one of their own, so that no
    # node's callback, nor a LoadNode waiting for a constructor, can keep
    # them from answering.
    executor = (
        MultiThreadedExecutor(context=context)
        if opts.use_multi_threaded_executor
        else SingleThreadedExecutor(context=context)
    )
    services = MultiThreadedExecutor(num_threads=SERVICE_THREADS, context=context)
    try:
        host = _make_host(opts, executor, context, node.get_logger())
    except SystemExit:
        node.destroy_node()
        rclpy.try_shutdown()
        raise
    manager = ComponentManager(node, host)
    if opts.isolated:
        host.on_death = manager.on_death
        if opts.restart_policy == "on-crash":
            manager.restart_policy = RestartPolicy(node, manager.reload)
    services.add_node(node)
    watchdog_s = opts.watchdog if opts.watchdog is not None else (10.0 if opts.isolated else 0.0)
    watchdog = None
    if watchdog_s > 0:
        # In isolated mode each tick also reads the progress board, so a lock
        # a dead child left on it is found and repaired even when idle.
        on_tick = host.board.snapshot if opts.isolated else None
        watchdog = Watchdog(node, watchdog_s, executors=[executor], on_tick=on_tick)
        manager.watchdog = watchdog
    node_watchdog = NodeWatchdog(node, host, opts.node_watchdog) if opts.node_watchdog > 0 else None
    failure: list[BaseException] = []
    spinner = threading.Thread(target=_spin, args=(executor, stop, failure), name="container-executor")
    spinner.start()
    server = threading.Thread(target=_serve, args=(services, node), name="container-services")
    server.start()
    node.get_logger().info(
        f"{node.get_fully_qualified_name()} ready "
        f"({'multi' if opts.use_multi_threaded_executor else 'single'}-threaded executor"
        f"{', isolated, profile ' + opts.profile if opts.isolated else ''}, {allocator.describe()})"
    )
    signum = stop.wait()
    if failure:
        # As with rclcpp: an exception escaping a callback ends the container.
        node.get_logger().fatal(f"stopping: a callback raised {type(failure[0]).__name__}: {failure[0]}")
    else:
        node.get_logger().info(f"stopping ({signal.Signals(signum).name})")
    # Stop serving first, then stop the nodes, then tear down our own DDS side.
    if watchdog is not None:
        watchdog.close()
    shutdown_s = opts.shutdown_timeout if opts.shutdown_timeout is not None else watchdog_s
    shutdown_bound = bound_shutdown(shutdown_s) if shutdown_s > 0 else None
    if node_watchdog is not None:
        node_watchdog.close()
    manager.stopping()                    # answer loads still waiting for their node
    services.shutdown()
    server.join()
    executor.shutdown()
    spinner.join()
    try:
        manager.close()
    except Exception:                     # shutdown goes on regardless
        node.get_logger().error("stopping the nodes failed:\n" + traceback.format_exc())
    node.destroy_node()
    rclpy.try_shutdown()
    # Destroying the context destroys its DDS participant now, which unlinks
    # its /dev/shm segments when the SHM transport is on.
    context.destroy()
    stop.close()
    if shutdown_bound is not None:
        shutdown_bound.close()
    if opts.isolated:
        # Objects a dead child left behind (see isolated/host.py) must never
        # be destroyed: the C++ static destructors that exit() runs would do
        # it (Fast DDS destroys every participant it still knows) and block
        # on a condition variable the dead child was waiting on. Everything
        # of ours is already stopped; flush and leave without them.
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(1 if failure else 0)
    return 1 if failure else 0


def _serve(services, node) -> None:
    """The services' executor: its callbacks contain their own failures
    (manager.py); should anything still escape, it is logged and serving
    goes on."""
    while True:
        try:
            services.spin()
            return                         # shut down
        except Exception:
            if not node.context.ok():
                return
            node.get_logger().error("a service callback raised (served on):\n" + traceback.format_exc())


def _spin(executor, stop: StopSignals, failure: list) -> None:
    try:
        executor.spin()
    except BaseException as exc:
        traceback.print_exc()
        failure.append(exc)
    finally:
        stop.post()   # if spin ended on its own (an error), the main thread stops too


if __name__ == "__main__":
    sys.exit(main())
