"""Process-per-node baseline: one component in a fork+exec'd Python process.

    python -m cloneguard.bench.process_per_node [--node-name NAME] [--param NAME:=VALUE ...] [--ready-fd FD]
                                                [--parent PID] PACKAGE PLUGIN
    python -m cloneguard.bench.process_per_node cloneguard cloneguard::Heartbeat

It finds the component class the way the container does (the
``cloneguard.components`` entry points, ``container.registry``), builds it on
an rclpy Context of its own (its own DDS participant), puts it on a
SingleThreadedExecutor and spins until SIGTERM or SIGINT. Once the node is
built and on its executor it writes one line to ``--ready-fd`` (default:
stdout):

    ready {"pid": ..., "main_ns": ..., "imported_ns": ..., "context_ns": ..., "ready_ns": ..., "full_name": "..."}

with CLOCK_MONOTONIC stamps of: the module's first line (the interpreter is
running Python), rclpy and the registry imported, the Context initialised,
the node built. ``--parent PID``: die (SIGKILL) with that process, and exit at
once if it is already gone.
"""

import time

MAIN_NS = time.monotonic_ns()  # the first line: this process is running Python

import argparse  # noqa: E402
import json  # noqa: E402
import os  # noqa: E402
import signal  # noqa: E402
import sys  # noqa: E402
from typing import Any  # noqa: E402

_PR_SET_PDEATHSIG = 1


def _die_with(parent: int) -> None:
    import ctypes

    libc = ctypes.CDLL(None, use_errno=True)
    if libc.prctl(_PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0) != 0:
        raise OSError(ctypes.get_errno(), "prctl(PR_SET_PDEATHSIG)")
    if os.getppid() != parent:  # it died before the line above
        os._exit(1)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m cloneguard.bench.process_per_node", description=__doc__.split("\n")[0]
    )
    parser.add_argument("package")
    parser.add_argument("plugin")
    parser.add_argument("--node-name", default="")
    parser.add_argument("--param", action="append", default=[], metavar="NAME:=VALUE", help="a ROS parameter")
    parser.add_argument("--ready-fd", type=int, default=1)
    parser.add_argument("--parent", type=int, default=0)
    opts = parser.parse_args(argv)
    if opts.parent:
        _die_with(opts.parent)

    stop = []
    signal.signal(signal.SIGTERM, lambda *_: stop.append(signal.SIGTERM))
    signal.signal(signal.SIGINT, lambda *_: stop.append(signal.SIGINT))

    import rclpy
    from rclpy.context import Context
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.signals import SignalHandlerOptions

    from cloneguard.container.registry import find

    imported_ns = time.monotonic_ns()

    cls = find(opts.package, opts.plugin).load_class()
    ctx = Context()
    rclpy.init(args=[], context=ctx, signal_handler_options=SignalHandlerOptions.NO)
    context_ns = time.monotonic_ns()
    cli_args = ["--ros-args"] + (["-r", f"__node:={opts.node_name}"] if opts.node_name else [])
    for param in opts.param:
        cli_args += ["-p", param]
    # A component's constructor takes Node's keywords but for its name (as construction.py).
    node_kwargs: dict[str, Any] = {"context": ctx, "cli_args": cli_args, "use_global_arguments": False}
    node = cls(**node_kwargs)
    executor = SingleThreadedExecutor(context=ctx)
    executor.add_node(node)
    ready_ns = time.monotonic_ns()

    line = (
        "ready "
        + json.dumps(
            {
                "pid": os.getpid(),
                "main_ns": MAIN_NS,
                "imported_ns": imported_ns,
                "context_ns": context_ns,
                "ready_ns": ready_ns,
                "full_name": node.get_fully_qualified_name(),
            }
        )
        + "\n"
    )
    os.write(opts.ready_fd, line.encode())
    if opts.ready_fd > 2:
        os.close(opts.ready_fd)

    # Signal handlers run between spins: the timeout bounds how long a stop waits.
    while not stop:
        executor.spin_once(timeout_sec=0.1)
    executor.shutdown()
    node.destroy_node()
    ctx.try_shutdown()
    ctx.destroy()
    return 0


if __name__ == "__main__":
    sys.exit(main())
