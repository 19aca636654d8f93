"""Find component classes among installed entry points.

A component is an ``rclpy.node.Node`` subclass that an installed distribution
registers in the ``cloneguard.components`` entry-point group, or in
``rclpy_components``, the group of rclpy's composition proposal (ros2/rclpy
PR #599), so that a component written for it loads unchanged. A LoadNode's
``package_name`` names the distribution, its ``plugin_name`` the entry point.
Only installed entry points are ever loaded: a request can never name a file
or an arbitrary module.

A component's ``__init__`` accepts the keyword arguments of
``rclpy.node.Node.__init__`` (context, cli_args, parameter_overrides, ...) and
forwards them to it, the way an rclcpp component takes ``NodeOptions``.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from importlib.metadata import EntryPoint, entry_points

from rclpy.node import Node

from . import spelling
from .options import LoadError

ENTRY_POINT_GROUP = "cloneguard.components"
# Searched too; where a distribution registers a name in both, ours wins.
RCLPY_COMPONENTS_GROUP = "rclpy_components"

# Upstream rclcpp_components' texts, kept word for word so clients that match
# on them behave the same with this container.
UNKNOWN_PACKAGE = "Could not find requested resource in ament index"
UNKNOWN_PLUGIN = "Failed to find class with the requested plugin name."


def _normalize(name: str) -> str:
    # Runs of - _ . are one separator (a distribution's name may be spelt
    # either way), but case counts: an ament package name is matched exactly.
    return re.sub(r"[-_.]+", "-", name)


@dataclass(frozen=True)
class ComponentSpec:
    package_name: str
    plugin_name: str
    entry_point: EntryPoint

    def load_class(self) -> type[Node]:
        try:
            cls = self.entry_point.load()
        except Exception as exc:  # an installed plugin that fails to import
            raise LoadError(
                f"Failed to import component {self.plugin_name!r} "
                f"({self.entry_point.value}): {type(exc).__name__}: {exc}"
            ) from None
        if not (isinstance(cls, type) and issubclass(cls, Node)):
            raise LoadError(
                f"Component {self.plugin_name!r} ({self.entry_point.value}) is not a subclass of rclpy.node.Node"
            )
        return cls


def _scan() -> dict[str, dict[str, EntryPoint]]:
    """Every installed component: {normalized distribution: {plugin: entry point}}.
    Reading every distribution's metadata takes milliseconds, so it is done
    once and again only when a request names something not seen yet."""
    index: dict[str, dict[str, EntryPoint]] = {}
    for group in (RCLPY_COMPONENTS_GROUP, ENTRY_POINT_GROUP):
        for ep in entry_points(group=group):
            if ep.dist is not None:
                index.setdefault(_normalize(ep.dist.name), {})[ep.name] = ep
    return index


_index: dict[str, dict[str, EntryPoint]] | None = None


def components_of(package_name: str) -> dict[str, EntryPoint]:
    """The entry points a distribution registers, by plugin name."""
    return (_index or {}).get(_normalize(package_name), {})


def find(package_name: str, plugin_name: str) -> ComponentSpec:
    """The component a LoadNode names; a LoadError with upstream's text if
    there is none, and in its log detail the names there are, the closest to
    the one asked for first."""
    global _index
    if _index is None or plugin_name not in components_of(package_name):
        _index = _scan()  # first use, or installed since the last scan?
    plugins = components_of(package_name)
    if not plugins:
        offered = spelling.closest_listed(package_name, _index) or "none"
        raise LoadError(
            UNKNOWN_PACKAGE, f"no package {package_name!r} has components; those that do, closest first: {offered}"
        )
    if plugin_name not in plugins:
        offered = spelling.closest_listed(plugin_name, plugins)
        raise LoadError(
            UNKNOWN_PLUGIN, f"package {package_name!r} has no plugin {plugin_name!r}; it has, closest first: {offered}"
        )
    return ComponentSpec(package_name, plugin_name, plugins[plugin_name])
