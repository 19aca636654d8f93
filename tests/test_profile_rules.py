"""--profile-for PATTERN=PROFILE (container/isolated/profiles.py): which
profile a node is built in, by its requested name or its plugin; the
command line refuses a bad rule; a container builds each node where its
rule says."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

from cloneguard.container.isolated.profiles import ProfileRule, choose, parse_rule

CONTAINER = os.path.join(sys.prefix, "bin", "component_container")


def test_the_first_rule_a_node_matches_by_name_or_plugin_wins():
    rules = [parse_rule("/planning/*=per-node"), parse_rule("demo_robot::Map*=per-node"), parse_rule("*=shared")]
    assert choose(rules, "/planning/planner", "demo_robot::Planner") == "per-node"
    assert choose(rules, "", "demo_robot::MapServer") == "per-node"  # unnamed: by its plugin
    assert choose(rules, "/odometry", "demo_robot::Odometry") == "shared"
    assert choose(rules[:2], "/odometry", "demo_robot::Odometry") is None  # the container's --profile
    assert parse_rule("/a=b=shared") == ProfileRule("/a=b", "shared")  # the last '=' splits


@pytest.mark.parametrize(
    "rule, says",
    [("/planning/*", "expected PATTERN=PROFILE"), ("=shared", "expected PATTERN=PROFILE"), ("/x=fast", "got 'fast'")],
)
def test_a_bad_rule_is_refused_saying_why(rule, says):
    proc = subprocess.run([CONTAINER, "--isolated", "--profile-for", rule], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2 and says in proc.stderr, proc.stderr
