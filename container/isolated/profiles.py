"""The isolated mode's participant profiles (see host.py for what each means),
and the rules that pick one per node by name (``--profile-for``).

Kept apart so the command line can list them without loading the C core."""

from __future__ import annotations

from dataclasses import dataclass
from fnmatch import fnmatchcase

PER_NODE = "per-node"
SHARED = "shared"
PROFILES = (PER_NODE, SHARED)
DEFAULT = SHARED


@dataclass(frozen=True)
class ProfileRule:
    """``--profile-for PATTERN=PROFILE``: nodes whose requested full name
    (``/namespace/name``, when the LoadNode names the node) or plugin
    (``package::Class``) matches PATTERN (fnmatch, case-sensitive) are built
    in PROFILE."""

    pattern: str
    profile: str

    def matches(self, full_name: str, plugin: str) -> bool:
        return (bool(full_name) and fnmatchcase(full_name, self.pattern)) or fnmatchcase(plugin, self.pattern)


def parse_rule(text: str) -> ProfileRule:
    """``PATTERN=PROFILE``; ValueError saying what is wrong."""
    pattern, sep, profile = text.rpartition("=")
    if not sep or not pattern:
        raise ValueError(f"expected PATTERN=PROFILE, got {text!r}")
    if profile not in PROFILES:
        raise ValueError(f"the profile after '=' must be one of {', '.join(PROFILES)}, got {profile!r}")
    return ProfileRule(pattern, profile)


def choose(rules: list[ProfileRule], full_name: str, plugin: str) -> str | None:
    """The profile of the first rule a node matches, or None."""
    return next((r.profile for r in rules if r.matches(full_name, plugin)), None)
