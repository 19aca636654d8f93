"""One look at a domain as ros2cli's `ros2 component list` takes it, from a
fresh process (a fresh DDS participant every time, as each ros2 command is):

    python -m cloneguard.bench._discovery_probe CONTAINER_FQN [--timeout S] [--nodes NAME ...]

It creates a node the way ros2cli's DirectNode does (no daemon), then spins
and polls the ROS graph every 10 ms until the container's node, its
``_container/list_nodes`` service and every node of ``--nodes`` (full
names: what `ros2 node list` is to show) are seen, and prints one JSON line:
{"node_s": ..., "service_s": ..., "all_nodes_s": ...} (seconds from the
node's creation; null if not seen within the timeout). ros2cli spins 0.5 s before it asks, so a
container whose service_s is above 0.5 is missing from `ros2 component
list`. The ROS environment (domain, Fast DDS profile) comes from the caller.
"""

import argparse
import json
import os
import time

import rclpy


def main() -> int:
    parser = argparse.ArgumentParser()
    parser.add_argument("fqn")
    parser.add_argument("--timeout", type=float, default=5.0)
    parser.add_argument("--nodes", nargs="*", default=[])
    args = parser.parse_args()
    expected = set(args.nodes)
    namespace, _, name = args.fqn.rpartition("/")
    namespace = namespace or "/"
    service = f"{args.fqn}/_container/list_nodes"
    rclpy.init()
    try:
        t0 = time.monotonic()
        node = rclpy.create_node(f"_ros2cli_{os.getpid()}", start_parameter_services=False)
        node_s = service_s = all_nodes_s = None
        while time.monotonic() - t0 < args.timeout and (service_s is None or all_nodes_s is None):
            rclpy.spin_once(node, timeout_sec=0.01)
            now = time.monotonic() - t0
            graph = node.get_node_names_and_namespaces()
            if node_s is None and (name, namespace) in graph:
                node_s = now
            if node_s is not None and service_s is None:
                services = node.get_service_names_and_types_by_node(name, namespace)
                if any(s == service for s, _ in services):
                    service_s = now
            if all_nodes_s is None and expected <= {f"{ns.rstrip('/')}/{n}" for n, ns in graph}:
                all_nodes_s = now
        node.destroy_node()
    finally:
        rclpy.try_shutdown()
    print(json.dumps({"node_s": node_s, "service_s": service_s, "all_nodes_s": all_nodes_s}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
