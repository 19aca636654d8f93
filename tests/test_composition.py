"""A composition read from a file (harness/composition.py): a launch file's
container in the XML and YAML launch formats, and a plain description;
what launch would evaluate and this reader does not is refused by name."""

import textwrap

import pytest

from cloneguard.harness.composition import CompositionError, read_composition
from cloneguard.harness.process import REPO_ROOT
from cloneguard.harness.system import NodeSpec

DEMO_LAUNCH = REPO_ROOT / "examples" / "demo_robot" / "launch" / "robot.launch.xml"
DEMO = (
    NodeSpec("demo_robot", "demo_robot::Odometry", parameters={"rate": 20.0}),
    NodeSpec("demo_robot", "demo_robot::Planner"),
    NodeSpec("demo_robot", "demo_robot::MapServer", parameters={"map": "warehouse"}),
)

YAML_LAUNCH = """
launch:
  - arg: {name: odom_rate, default: "20.0"}
  - node_container:
      pkg: cloneguard
      exec: component_container
      name: robot_container
      namespace: ""
      args: --isolated
      composable_node:
        - pkg: demo_robot
          plugin: demo_robot::Odometry
          param:
            - {name: rate, value: $(var odom_rate)}
        - {pkg: demo_robot, plugin: demo_robot::Planner}
  - load_composable_node:
      target: robot_container
      composable_node:
        - pkg: demo_robot
          plugin: demo_robot::MapServer
          param:
            - {name: map, value: warehouse}
"""


def _write(tmp_path, name, text):
    path = tmp_path / name
    path.write_text(textwrap.dedent(text))
    return path


def test_the_demo_robots_launch_file_is_its_composition():
    comp = read_composition(DEMO_LAUNCH)
    assert comp.nodes == DEMO and comp.container_args == ("--isolated",)


def test_the_yaml_launch_format_reads_the_same(tmp_path):
    comp = read_composition(_write(tmp_path, "robot.launch.yaml", YAML_LAUNCH))
    assert comp.nodes == DEMO and comp.container_args == ("--isolated",)


def test_launch_arguments_typed_remaps_names_and_extra_arguments(tmp_path):
    path = _write(
        tmp_path,
        "a.launch.xml",
        """
        <launch>
          <arg name="ns" default="robot"/>
          <node_container pkg="rclcpp_components" exec="component_container" name="c" namespace="/$(var ns)">
            <composable_node pkg="p" plugin="p::N" name="n" namespace="$(var ns)">
              <param name="count" value="3"/><param name="on" value="true"/><param name="ids" value="[1, 2]"/>
              <remap from="/in" to="/$(var ns)/in"/>
              <extra_arg name="use_intra_process_comms" value="true"/>
            </composable_node>
          </node_container>
          <load_composable_node target="/$(var ns)/c"><composable_node pkg="p" plugin="p::M"/></load_composable_node>
          <load_composable_node target="/elsewhere"><composable_node pkg="p" plugin="p::X"/></load_composable_node>
        </launch>
    """,
    )
    comp = read_composition(path, args={"ns": "rover"})
    [n, m] = comp.nodes
    assert n == NodeSpec("p", "p::N", "n", "rover", {"count": 3, "on": True, "ids": [1, 2]}, {"/in": "/rover/in"},
                         {"use_intra_process_comms": True})  # fmt: skip
    assert m.plugin == "p::M"  # loaded into this container; /elsewhere's is not
    assert comp.container_args is None  # an rclcpp container's args say nothing of ours


def test_a_plain_description(tmp_path):
    path = _write(
        tmp_path,
        "robot.yaml",
        """
        container_args: [--isolated, --profile, shared]
        nodes:
          - {package: demo_robot, plugin: demo_robot::Odometry, parameters: {rate: 20.0}, remaps: {/odom: /o}}
          - {package: demo_robot, plugin: demo_robot::Planner, name: p2}
    """,
    )
    comp = read_composition(path)
    assert comp.container_args == ("--isolated", "--profile", "shared")
    assert comp.nodes == (
        NodeSpec("demo_robot", "demo_robot::Odometry", parameters={"rate": 20.0}, remaps={"/odom": "/o"}),
        NodeSpec("demo_robot", "demo_robot::Planner", name="p2"),
    )


CONTAINER = '<node_container pkg="cloneguard" exec="component_container" name="c" namespace="">{}</node_container>'


@pytest.mark.parametrize(
    "name, text, says",
    [
        ("robot.launch.py", "def generate_launch_description(): ...", "only launch can run"),
        ("robot.txt", "x", "not .txt"),
        ("a.xml", "<launch><node_container", "not well-formed"),
        ("a.xml", "<root/>", "not <launch>"),
        ("a.xml", "<launch>" + CONTAINER.format('<composable_node pkg="$(find-pkg-share p)" plugin="p::N"/>')
         + "</launch>", "$(find-pkg-share p) is not evaluated"),
        ("a.xml", "<launch>" + CONTAINER.format('<composable_node pkg="p" plugin="p::N"><param from="x.yaml"/>'
         "</composable_node>") + "</launch>", "a parameter file"),
        ("a.xml", '<launch><include file="x.launch.xml"/></launch>', "<include> is not read here"),
        ("a.xml", "<launch>" + CONTAINER.format("") + CONTAINER.format("") + "</launch>", "name one with container="),
        ("a.xml", "<launch>" + CONTAINER.format("") + "</launch>", "has no composable_node"),
        ("a.xml", "<launch>" + CONTAINER.format('<composable_node pkg="p" plugin="p::N" respawn="true"/>')
         + "</launch>", "['respawn'] not read here"),
        ("a.xml", "<launch>" + CONTAINER.format('<composable_node pkg="$(var nope)" plugin="p::N"/>')
         + "</launch>", "$(var nope) names no launch argument"),
        ("a.xml", '<launch><arg name="x"/></launch>', "has no default"),
        ("a.yaml", "nodes: [{plugin: p::N}]", "needs a package and a plugin"),
        ("a.yaml", "nodes: [{package: p, plugin: p::N, params: {}}]", "['params'] not known"),
        ("a.yaml", "something: else", "neither a launch file"),
    ],
)  # fmt: skip
def test_what_is_not_read_is_refused_by_name(tmp_path, name, text, says):
    with pytest.raises(CompositionError) as info:
        read_composition(_write(tmp_path, name, text))
    assert says in str(info.value) and name in str(info.value)


def test_a_container_is_chosen_by_name(tmp_path):
    two = "<launch>" + CONTAINER.format('<composable_node pkg="p" plugin="p::A"/>').replace('name="c"', 'name="a"')
    two += CONTAINER.format('<composable_node pkg="p" plugin="p::B"/>').replace('name="c"', 'name="b"') + "</launch>"
    path = _write(tmp_path, "two.launch.xml", two)
    assert [n.plugin for n in read_composition(path, container="b").nodes] == ["p::B"]
    with pytest.raises(CompositionError, match=r"no node_container named 'z'; it has \['a', 'b'\]"):
        read_composition(path, container="z")
