"""A Fast DDS discovery server of the benchmark's own, for measuring the
node participants' discovery without multicast.

Under ``ROS_DISCOVERY_SERVER`` (ROS 2's own way to use one) every
participant is a client: it learns of the others through the server, and
only of those whose endpoints match its own, instead of every participant
learning every other one and each of its endpoints. The server is a
process of the benchmark's own (``python -m
cloneguard.bench.discovery_server``): one rclpy participant under the
harness's no-SHM profile turned into a SERVER, with the prefix
``ROS_DISCOVERY_SERVER`` gives server 0 and a unicast locator on
127.0.0.1. (Fast DDS's ``fastdds discovery`` tool would add its
shared-memory transport, and its segments, whatever its profile says.)

The variable is read once per process, at its first participant: a
benchmark run under a server is under it for good (``bench.scale
--discovery-server`` runs alone for that reason), and the containers and
runners it starts inherit it.
"""

from __future__ import annotations

import argparse
import os
import signal
import socket
import subprocess
import sys
import tempfile
import time
import xml.etree.ElementTree as ET
from pathlib import Path

from cloneguard.harness.process import NO_SHM_PROFILE, REPO_ROOT, process_environment, stop_group

VARIABLE = "ROS_DISCOVERY_SERVER"
#: The GUID prefix Fast DDS expects of the server at index 0 of
#: ROS_DISCOVERY_SERVER (its third byte is the index).
SERVER_PREFIX = "44.53.00.5f.45.50.52.4f.53.49.4d.41"
READY = "discovery server ready"
MOST = "discovery server: most nodes known at once:"
_NS = "http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles"


def server_profile(port: int, base: Path = NO_SHM_PROFILE) -> str:
    """``base``'s default participant profile made a discovery SERVER
    listening on 127.0.0.1:``port``."""
    ET.register_namespace("", _NS)
    tree = ET.parse(base)

    def q(tag: str) -> str:
        return f"{{{_NS}}}{tag}"

    [rtps] = [p.find(q("rtps")) for p in tree.iter(q("participant")) if p.get("is_default_profile") == "true"]
    if rtps is None:
        raise ValueError(f"{base}: the default participant profile has no <rtps>")
    ET.SubElement(rtps, q("prefix")).text = SERVER_PREFIX
    builtin = rtps.find(q("builtin"))
    if builtin is None:
        builtin = ET.SubElement(rtps, q("builtin"))
    discovery = builtin.find(q("discovery_config"))
    if discovery is None:
        discovery = ET.SubElement(builtin, q("discovery_config"))
    discovery.insert(0, ET.Element(q("discoveryProtocol")))
    discovery[0].text = "SERVER"
    udp = ET.SubElement(
        ET.SubElement(ET.SubElement(builtin, q("metatrafficUnicastLocatorList")), q("locator")), q("udpv4")
    )
    ET.SubElement(udp, q("address")).text = "127.0.0.1"
    ET.SubElement(udp, q("port")).text = str(port)
    return ET.tostring(tree.getroot(), encoding="unicode")


def _free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class DiscoveryServer:
    """The server process, in a process group of its own; :meth:`stop` ends it."""

    def __init__(self, domain_id: int, log_path: Path, timeout: float = 30.0):
        self.port = _free_udp_port()
        env = process_environment(domain_id)
        env["PYTHONUNBUFFERED"] = "1"
        self.log_path = Path(log_path)
        self._log = open(self.log_path, "ab", buffering=0)
        try:
            # setpriv: it dies with the benchmark, whatever ends that.
            self.popen = subprocess.Popen(
                [
                    "setpriv",
                    "--pdeathsig",
                    "KILL",
                    "--",
                    sys.executable,
                    "-m",
                    "cloneguard.bench.discovery_server",
                    "--port",
                    str(self.port),
                ],  # fmt: skip
                cwd=REPO_ROOT,
                env=env,
                stdin=subprocess.DEVNULL,
                stdout=self._log,
                stderr=subprocess.STDOUT,
                start_new_session=True,
            )
        except BaseException:
            self._log.close()
            raise
        self.pid = self.pgid = self.popen.pid
        deadline = time.monotonic() + timeout
        while READY not in self.log_path.read_text(errors="replace"):
            if self.popen.poll() is not None or time.monotonic() > deadline:
                self.stop()
                raise RuntimeError(
                    f"the discovery server did not start (exit {self.popen.poll()}):\n"
                    + self.log_path.read_text(errors="replace")[-2000:]
                )
            time.sleep(0.05)

    @property
    def address(self) -> str:
        """ROS_DISCOVERY_SERVER's value for it."""
        return f"127.0.0.1:{self.port}"

    def most_nodes(self) -> int | None:
        """After :meth:`stop`: the most nodes the server knew of at once (the
        clients' nodes, its own included); None if it did not say."""
        for line in self.log_path.read_text(errors="replace").splitlines():
            if line.startswith(MOST):
                return int(line[len(MOST) :])
        return None

    def stop(self, grace: float = 5.0) -> int:
        code, _ = stop_group(self.popen, self.pgid, grace)
        if not self._log.closed:
            self._log.close()
        return code


def serve(port: int) -> None:
    """In the server process: its participant, listening on
    127.0.0.1:``port``, until SIGTERM or SIGINT."""
    signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGTERM, signal.SIGINT})
    with tempfile.NamedTemporaryFile("w", prefix="cloneguard-discovery-server-", suffix=".xml") as profile:
        profile.write(server_profile(port))
        profile.flush()
        # Read by Fast DDS at this process's first participant; a server is no client.
        os.environ["FASTRTPS_DEFAULT_PROFILES_FILE"] = profile.name
        os.environ.pop(VARIABLE, None)
        _serve(port)


def _serve(port: int) -> None:
    import rclpy
    from rclpy.context import Context
    from rclpy.signals import SignalHandlerOptions

    ctx = Context()
    rclpy.init(context=ctx, signal_handler_options=SignalHandlerOptions.NO)
    node = rclpy.create_node("_discovery_server", context=ctx)
    print(f"{READY} (pid {os.getpid()}): {VARIABLE}=127.0.0.1:{port}", flush=True)
    most = 0
    while signal.sigtimedwait({signal.SIGTERM, signal.SIGINT}, 0.25) is None:
        most = max(most, len(node.get_node_names()))
    print(f"{MOST} {most}", flush=True)
    node.destroy_node()
    rclpy.shutdown(context=ctx)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(
        prog="python -m cloneguard.bench.discovery_server",
        description="A Fast DDS discovery server (server 0 of ROS_DISCOVERY_SERVER) on 127.0.0.1, "
        "UDP only, no shared memory, until SIGTERM or Ctrl-C.",
    )
    parser.add_argument("--port", type=int, default=11811, help="its UDP port (default: %(default)s)")
    serve(parser.parse_args(argv).port)


if __name__ == "__main__":
    main()
