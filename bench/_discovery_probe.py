"""One look at a domain as ros2cli's `ros2 component list` takes it, from a
fresh process (a fresh DDS participant every time, as each ros2 command is):

    python -m cloneguard.bench._discovery_probe CONTAINER_FQN [--timeout S]

It creates a node the way ros2cli's DirectNode does (no daemon), then spins
and polls the ROS graph every 10 ms until the container's node and its
``_container/list_nodes`` service are both seen, and prints one JSON line:
{"node_s": ..., "service_s": ...} (seconds from the node's creation; null
if not seen within the timeout). ros2cli spins 0.5 s before it asks, so a
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
    args = parser.parse_args()
    namespace, _, name = args.fqn.rpartition("/")
    namespace = namespace or "/"
    service = f"{args.fqn}/_container/list_nodes"
    rclpy.init()
    try:
        t0 = time.monotonic()
        node = rclpy.create_node(f"_ros2cli_{os.getpid()}", start_parameter_services=False)
        node_s = service_s = None
        while time.monotonic() - t0 < args.timeout and service_s is None:
            rclpy.spin_once(node, timeout_sec=0.01)
            now = time.monotonic() - t0
            if node_s is None and (name, namespace) in node.get_node_names_and_namespaces():
                node_s = now
            if node_s is not None:
                services = node.get_service_names_and_types_by_node(name, namespace)
                if any(s == service for s, _ in services):
                    service_s = now
        node.destroy_node()
    finally:
        rclpy.try_shutdown()
    print(json.dumps({"node_s": node_s, "service_s": service_s}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
