"""Your composition read from a file: the composable nodes of a ROS 2 launch
file's container (XML or YAML launch format), or a plain YAML description.

    from cloneguard.harness.composition import read_composition

    robot = system_factory(read_composition("launch/robot.launch.xml"))

What is read from a launch file (the launch_ros front end's names): the
one ``node_container`` (or the one named ``container=``) with its
``args``, its ``composable_node`` children, and the ``composable_node``s of
every ``load_composable_node`` whose ``target`` is that container; of each
node ``pkg``, ``plugin``, ``name``, ``namespace``, ``param`` (``name`` and
``value``), ``remap`` (``from``, ``to``) and ``extra_arg``. ``$(var X)``
takes the launch file's ``arg`` X (its ``default``, or ``args={X: ...}``).
Anything else that launch would evaluate (another substitution, a
``param from=`` file, an ``include``, a condition) is refused by name
rather than guessed: this reader is not launch. Python launch files need
launch itself to run; they are refused with that reason.

A plain description (YAML) is what ``NodeSpec`` holds::

    container_args: [--isolated]
    nodes:
      - package: demo_robot
        plugin: demo_robot::Odometry
        parameters: {rate: 20.0}
        remaps: {/odom: /odom_raw}

Public and kept stable, like system.py.
"""

from __future__ import annotations

import re
import shlex
import xml.etree.ElementTree as ET
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml

from .system import NodeSpec

_SUBSTITUTION = re.compile(r"\$\(([^)]*)\)")
_NODE_KEYS = {"pkg", "plugin", "name", "namespace", "param", "remap", "extra_arg"}


class CompositionError(ValueError):
    """The file does not describe a composition this reader can take; the
    message names the file and what."""


@dataclass(frozen=True)
class Composition:
    """The nodes to load, in order, and the container's arguments: the
    launch file's ``args`` when its container is cloneguard's
    (``pkg="cloneguard"``), the description's ``container_args``; None
    when the file does not say (``system_factory`` then isolates)."""

    nodes: tuple[NodeSpec, ...]
    container_args: tuple[str, ...] | None = None
    source: str = ""


def read_composition(
    path: str | Path, *, container: str | None = None, args: Mapping[str, str] | None = None
) -> Composition:
    """The composition ``path`` describes (by its ending: ``.xml``,
    ``.yaml``/``.yml``; ``.py`` is refused). ``container``: the name of the
    launch file's container, where it has several. ``args``: values of its
    launch arguments."""
    path = Path(path)
    text = path.read_text()
    if path.suffix == ".py":
        raise CompositionError(
            f"{path}: a Python launch file is a program that only launch can run (not installed here); "
            "write the container in the XML or YAML launch format, or as a plain YAML description"
        )
    if path.suffix == ".xml":
        entities = _xml_entities(path, text)
    elif path.suffix in (".yaml", ".yml"):
        data = yaml.safe_load(text)
        if isinstance(data, Mapping) and "nodes" in data:
            return _plain(path, data)
        if not isinstance(data, Mapping) or not isinstance(data.get("launch"), list):
            raise CompositionError(f"{path}: neither a launch file (a 'launch:' list) nor a description ('nodes:')")
        entities = [_yaml_entity(path, item) for item in data["launch"]]
    else:
        raise CompositionError(f"{path}: a composition is read from .xml, .yaml or .yml, not {path.suffix or 'none'}")
    return _from_launch(path, entities, container, dict(args or {}))


# -- one shape for both launch formats: (tag, attributes, children) ----------------------


@dataclass
class _Entity:
    tag: str
    attrs: dict[str, Any]
    children: list[_Entity]


def _xml_entities(path: Path, text: str) -> list[_Entity]:
    try:
        root = ET.fromstring(text)
    except ET.ParseError as exc:
        raise CompositionError(f"{path}: not well-formed XML: {exc}") from None
    if root.tag != "launch":
        raise CompositionError(f"{path}: the root element is <{root.tag}>, not <launch>")

    def entity(el: ET.Element) -> _Entity:
        return _Entity(el.tag, dict(el.attrib), [entity(c) for c in el])

    return [entity(el) for el in root]


def _yaml_entity(path: Path, item: object) -> _Entity:
    if not isinstance(item, Mapping) or len(item) != 1:
        raise CompositionError(f"{path}: each item of 'launch:' is one action, e.g. '- node_container: ...'")
    [(tag, body)] = item.items()
    attrs: dict[str, Any] = {}
    children: list[_Entity] = []
    for key, value in (body or {}).items():
        if isinstance(value, list) and all(isinstance(v, Mapping) for v in value):
            children.extend(_yaml_entity(path, {key: v}) for v in value)
        else:
            attrs[key] = value
    return _Entity(tag, attrs, children)


# -- launch semantics, the part this reader takes ----------------------------------------


def _from_launch(path: Path, entities: list[_Entity], wanted: str | None, given: dict[str, str]) -> Composition:
    values = dict(given)
    containers, loads = [], []
    for ent in entities:
        if ent.tag == "arg":
            name = str(ent.attrs.get("name", ""))
            if not name:
                raise CompositionError(f"{path}: an arg without a name")
            if name not in values:
                if "default" not in ent.attrs:
                    raise CompositionError(
                        f"{path}: launch argument {name!r} has no default: give args={{{name!r}: ...}}"
                    )
                values[name] = _text(path, ent.attrs["default"], values)
        elif ent.tag == "node_container":
            containers.append(ent)
        elif ent.tag == "load_composable_node":
            loads.append(ent)
        else:
            raise CompositionError(
                f"{path}: <{ent.tag}> is not read here (only arg, node_container, load_composable_node)"
            )
    names = [_text(path, c.attrs.get("name", ""), values) for c in containers]
    if wanted is not None:
        if wanted not in names:
            raise CompositionError(f"{path}: no node_container named {wanted!r}; it has {names}")
        chosen = containers[names.index(wanted)]
    elif len(containers) == 1:
        chosen = containers[0]
    else:
        raise CompositionError(f"{path}: {len(containers)} node_containers ({names}): name one with container=")
    name = _text(path, chosen.attrs.get("name", ""), values)
    namespace = _text(path, chosen.attrs.get("namespace", ""), values).strip("/")
    full = f"/{namespace}/{name}" if namespace else f"/{name}"
    nodes = [_node(path, c, values) for c in chosen.children if c.tag == "composable_node"]
    for load in loads:
        target = _text(path, load.attrs.get("target", ""), values)
        if target in (name, full):
            nodes.extend(_node(path, c, values) for c in load.children if c.tag == "composable_node")
    if not nodes:
        raise CompositionError(f"{path}: container {full} has no composable_node")
    ours = _text(path, chosen.attrs.get("pkg", ""), values) == "cloneguard"
    container_args = tuple(shlex.split(_text(path, chosen.attrs.get("args", ""), values))) if ours else None
    return Composition(tuple(nodes), container_args, str(path))


def _node(path: Path, ent: _Entity, values: dict) -> NodeSpec:
    unknown = (set(ent.attrs) | {c.tag for c in ent.children}) - _NODE_KEYS
    if unknown:
        raise CompositionError(
            f"{path}: composable_node {ent.attrs.get('plugin', '?')}: {sorted(unknown)} not read here"
        )
    params, remaps, extra = {}, {}, {}
    for child in ent.children:
        if child.tag == "param":
            if "from" in child.attrs:
                raise CompositionError(
                    f"{path}: <param from=...> (a parameter file) is not read here; give name and value"
                )
            params[_text(path, child.attrs["name"], values)] = _value(path, child.attrs.get("value"), values)
        elif child.tag == "remap":
            remaps[_text(path, child.attrs["from"], values)] = _text(path, child.attrs["to"], values)
        elif child.tag == "extra_arg":
            extra[_text(path, child.attrs["name"], values)] = _value(path, child.attrs.get("value"), values)
    return NodeSpec(
        package=_text(path, ent.attrs.get("pkg", ""), values),
        plugin=_text(path, ent.attrs.get("plugin", ""), values),
        name=_text(path, ent.attrs.get("name", ""), values),
        namespace=_text(path, ent.attrs.get("namespace", ""), values),
        parameters=params,
        remaps=remaps,
        extra_arguments=extra,
    )


def _text(path: Path, raw: object, values: dict) -> str:
    """A launch string with its ``$(var X)`` replaced; any other
    substitution refused by name."""

    def one(match: re.Match[str]) -> str:
        words = match.group(1).split()
        if len(words) == 2 and words[0] == "var":
            if words[1] not in values:
                raise CompositionError(f"{path}: $(var {words[1]}) names no launch argument")
            return str(values[words[1]])
        raise CompositionError(f"{path}: the substitution $({match.group(1)}) is not evaluated here (only $(var X))")

    return _SUBSTITUTION.sub(one, str(raw))


def _value(path: Path, raw: object, values: dict) -> object:
    """A parameter's value: YAML's types (as launch types them: 20 an int,
    20.0 a float, true a bool, a list), from text after substitution."""
    if raw is None:
        raise CompositionError(f"{path}: a param or extra_arg without a value")
    if not isinstance(raw, str):
        return raw  # YAML launch files are typed already
    return yaml.safe_load(_text(path, raw, values))


def _plain(path: Path, data: Mapping) -> Composition:
    nodes = data.get("nodes")
    if not isinstance(nodes, Sequence) or not nodes:
        raise CompositionError(f"{path}: 'nodes' is a list of at least one node")
    fields = {"package", "plugin", "name", "namespace", "parameters", "remaps", "extra_arguments"}
    specs = []
    for i, node in enumerate(nodes):
        if not isinstance(node, Mapping) or not {"package", "plugin"} <= set(node):
            raise CompositionError(f"{path}: node {i} needs a package and a plugin")
        unknown = set(node) - fields
        if unknown:
            raise CompositionError(f"{path}: node {i}: {sorted(unknown)} not known (a node has {sorted(fields)})")
        kwargs: dict[str, Any] = {k: (dict(v) if isinstance(v, Mapping) else str(v)) for k, v in node.items()}
        specs.append(NodeSpec(**kwargs))
    args = data.get("container_args")
    if args is not None and not isinstance(args, list):
        raise CompositionError(f"{path}: container_args is a list of arguments")
    return Composition(tuple(specs), None if args is None else tuple(str(a) for a in args), str(path))
