"""The product installed alone: a wheel of cloneguard (the root
pyproject.toml), without its test rig, in a fresh venv, serves LoadNode and
cannot load a fault or benchmark component.

The fresh venv gets the product's dependencies (rclpy, the interface
packages, cffi) from this venv's site-packages through a directory of links
that leaves out both cloneguard distributions, so nothing of the rig can
leak in.
"""

import os
import shutil
import subprocess
import sys
import sysconfig
import zipfile
from pathlib import Path

import pytest
from cloneguard_interfaces.msg import ComponentEvent

from cloneguard.faults import PACKAGE as TESTRIG
from cloneguard.harness import domains
from cloneguard.harness.factory import ContainerFactory

REPO = Path(__file__).resolve().parent.parent
OURS = ("cloneguard-", "cloneguard_testrig-", "__editable__.cloneguard")


def _run(*argv, **kw):
    return subprocess.run(argv, check=True, capture_output=True, text=True, **kw)


@pytest.fixture(scope="module")
def product(tmp_path_factory) -> tuple[Path, Path]:
    """(the product's wheel, a fresh venv it is installed in)"""
    root = tmp_path_factory.mktemp("product")
    # Built from the repository's files alone, as a clean clone would be
    # (no build/ directory left by the editable installs).
    source = root / "source"
    for name in _run("git", "ls-files", cwd=REPO).stdout.splitlines():
        if (REPO / name).is_file():
            (source / name).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(REPO / name, source / name)
    _run(
        sys.executable,
        "-m",
        "pip",
        "wheel",
        "--no-deps",
        "--no-build-isolation",
        "-q",
        "-w",
        str(root / "dist"),
        str(source),
        cwd=root,
    )
    [wheel] = (root / "dist").glob("cloneguard-*.whl")
    venv = root / "venv"
    _run(sys.executable, "-m", "venv", "--without-pip", str(venv))
    deps = root / "deps"
    deps.mkdir()
    for entry in Path(sysconfig.get_paths()["purelib"]).iterdir():
        if not entry.name.startswith(OURS) and entry.name != "cloneguard":
            (deps / entry.name).symlink_to(entry)
    site = Path(
        _run(
            str(venv / "bin" / "python"), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"
        ).stdout.strip()
    )
    (site / "deps.pth").write_text(f"{deps}\n")
    _run(
        sys.executable,
        "-m",
        "pip",
        "--python",
        str(venv / "bin" / "python"),
        "install",
        "--no-deps",
        "--no-index",
        "-q",
        str(wheel),
    )
    return wheel, venv


def test_the_product_wheel_holds_only_the_container(product):
    wheel, _ = product
    with zipfile.ZipFile(wheel) as zf:
        names = zf.namelist()
        tops = {n.split("/")[0] for n in names}
        [entry_points] = [n for n in names if n.endswith(".dist-info/entry_points.txt")]
        declared = zf.read(entry_points).decode()
    # One top-level name, the project's namespace (no bare `container`),
    # holding only the container.
    assert {t for t in tops if not t.endswith((".dist-info", ".data"))} == {"cloneguard"}, tops
    assert {n.split("/")[1] for n in names if n.startswith("cloneguard/")} == {"container"}, names
    assert "cloneguard/__init__.py" not in names  # a namespace the rig's distribution shares
    # Besides the package, only the ament index entries (ament/README.md).
    data = sorted(n.split(".data/data/")[1] for n in names if ".data/" in n)
    assert data == [
        "lib/cloneguard/cloneguard-python-components.not-a-library",
        "lib/cloneguard/component_container",
        "share/ament_index/resource_index/packages/cloneguard",
        "share/ament_index/resource_index/rclcpp_components/cloneguard",
    ], data
    assert "faults" not in declared and "bench" not in declared and "pytest11" not in declared, declared
    assert any(n.startswith("cloneguard/container/isolated/_clonecore") for n in names)


def test_a_product_install_serves_loads_and_refuses_every_fault_component(product, tmp_path):
    _, venv = product
    python = venv / "bin" / "python"
    # The rig is not importable there at all.
    probe = subprocess.run([str(python), "-c", "import cloneguard.faults"], capture_output=True, text=True, cwd="/")
    assert probe.returncode != 0 and "No module named 'cloneguard.faults'" in probe.stderr
    exe = venv / "bin" / "component_container"
    assert exe.exists()
    # Where launch looks for it (<prefix>/lib/<package>), installed executable.
    assert os.access(venv / "lib" / "cloneguard" / "component_container", os.X_OK)
    with domains.lease() as lease:
        factory = ContainerFactory(lease.domain_id, tmp_path, exe=str(exe))
        try:
            container = factory.start([])
            client = factory.connect(container)
            ok = client.load_ok("cloneguard", "cloneguard::Heartbeat")
            # The container runs the installed product, not this checkout.
            maps = Path(f"/proc/{container.pid}/maps").read_text()
            assert str(venv) in maps and str(REPO / "container") not in maps
            for plugin in (
                "faults::SegfaultInCallback",
                "faults::DieHoldingContainerLock",
                "faults::MallocHammer",
                "bench::PayloadSource",
            ):
                # As upstream answers: no such package, or no such class in it.
                resp = client.load(TESTRIG, plugin)
                assert (resp.success, resp.error_message) == (False, "Could not find requested resource in ament index")
                resp = client.load("cloneguard", plugin)
                assert (resp.success, resp.error_message) == (
                    False,
                    "Failed to find class with the requested plugin name.",
                )
            # The rig's fault switches do not exist there: this one is an
            # unknown extra argument, ignored, and LOADED is sent.
            dropped = client.load_ok(
                "cloneguard",
                "cloneguard::Heartbeat",
                node_name="still_announced",
                extra_arguments={"cloneguard.fault.drop_loaded_event": True},
            )
            client.wait_for_event(ComponentEvent.LOADED, unique_id=dropped.unique_id)
            assert client.list() == [(ok.unique_id, "/heartbeat"), (dropped.unique_id, "/still_announced")]
        finally:
            factory.stop_all()
