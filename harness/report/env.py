"""What a report says about the machine and the code it ran on."""

from __future__ import annotations

import os
import platform
import subprocess
import sys
import tomllib
from importlib import metadata
from pathlib import Path

#: The stack under test whose versions every report names: the container,
#: its test rig, rclpy and Fast DDS with its rmw.
STACK = ("cloneguard", "cloneguard-testrig", "ros-jazzy-rclpy", "ros-rmw-fastrtps-cpp", "ros-fastrtps")
#: The entry point group of loadable components: the distributions that
#: declare some are the project's own nodes (or the rig's).
COMPONENT_GROUP = "cloneguard.components"


def cpuinfo(path: str = "/proc/cpuinfo") -> tuple[str | None, set[str]]:
    model: str | None = None
    flags: set[str] = set()
    try:
        with open(path, encoding="utf-8", errors="replace") as fh:
            for line in fh:
                key, _, value = line.partition(":")
                key = key.strip()
                if key == "model name" and model is None:
                    model = value.strip()
                elif key == "flags" and not flags:
                    flags = set(value.split())
                if model is not None and flags:
                    break
    except OSError:
        pass
    return model, flags


def host_info() -> dict:
    """Kernel, glibc, CPU model and count, and whether the CPU has PKU
    (memory protection keys: what per-node isolation inside one address
    space can use)."""
    uname = os.uname()
    try:
        glibc = os.confstr("CS_GNU_LIBC_VERSION")
    except (ValueError, OSError, AttributeError):
        glibc = None
    model, flags = cpuinfo()
    try:
        usable = len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        usable = None
    return {
        "hostname": uname.nodename,
        "kernel": uname.release,
        "machine": uname.machine,
        "glibc": glibc,
        "cpu_model": model or platform.processor() or None,
        "cpu_count": os.cpu_count(),
        "cpu_usable": usable,
        "pku": "pku" in flags,
        "ospke": "ospke" in flags,
    }


def python_version() -> str:
    return f"{platform.python_implementation()} {sys.version.split()[0]}"


def _git(repo: Path, *args: str) -> str | None:
    try:
        done = subprocess.run(
            ["git", "-C", str(repo), *args],
            capture_output=True,
            text=True,
            timeout=10,
            check=False,
        )
    except (OSError, subprocess.SubprocessError):
        return None
    return done.stdout.strip() if done.returncode == 0 else None


def git_info(repo: Path) -> dict:
    """Commit, branch and whether tracked files differ from it; {} without git."""
    commit = _git(repo, "rev-parse", "HEAD")
    if not commit:
        return {}
    status = _git(repo, "status", "--porcelain", "--untracked-files=no")
    branch = _git(repo, "rev-parse", "--abbrev-ref", "HEAD")
    return {
        "commit": commit,
        "branch": branch,
        "dirty": bool(status) if status is not None else None,
    }


def package_versions() -> dict[str, str]:
    """Name -> version of the stack (STACK) and of every installed package
    that declares components (the nodes a run can load)."""
    names = list(STACK)
    for dist in metadata.distributions():
        if any(ep.group == COMPONENT_GROUP for ep in dist.entry_points):
            name = dist.metadata["Name"]
            if name and name not in names:
                names.append(name)
    out = {}
    for name in names:
        try:
            out[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            continue
    return out


def project_name(invoked_in: Path, root: Path) -> str:
    """The project a run tested: the [project] name of the nearest
    pyproject.toml from where pytest was invoked up to its root directory
    (a package nested in a larger checkout is its own project), else the
    root directory's name."""
    here, root = Path(invoked_in).resolve(), Path(root).resolve()
    for d in (here, *here.parents):
        try:
            with open(d / "pyproject.toml", "rb") as fh:
                name = tomllib.load(fh).get("project", {}).get("name")
        except (OSError, tomllib.TOMLDecodeError):
            name = None
        if name:
            return str(name)
        if d == root:
            break
    return root.name
