"""The set-up venv is an ament prefix: launch_ros and ``ros2 component``
find cloneguard, its container executable and its component types the way
they find an rclcpp package (ament/README.md).

launch and ros2cli are not installable on this machine (no wheels), so the
lookups are made here with ament_index_python, as they make them:
launch_ros's ExecutableInPackage takes get_package_prefix(package), then
<prefix>/lib/<package>, then the executable found there; ros2component's
`types` reads the `rclcpp_components` resource and keeps what is before ';'.
"""

import os
import shutil
import signal
import sys
import tomllib
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent


@pytest.fixture
def ament_prefix(monkeypatch):
    """AMENT_PREFIX_PATH as `.venv/bin/activate` sets it."""
    monkeypatch.setenv("AMENT_PREFIX_PATH", sys.prefix)
    return sys.prefix


def _product_component_types() -> list[str]:
    with open(REPO / "pyproject.toml", "rb") as f:
        project = tomllib.load(f)["project"]
    return list(project["entry-points"]["cloneguard.components"])


def test_launch_finds_the_container_executable_in_the_package(ament_prefix):
    from ament_index_python.packages import get_package_prefix

    prefix = get_package_prefix("cloneguard")
    assert os.path.samefile(prefix, ament_prefix)
    libexec = os.path.join(prefix, "lib", "cloneguard")
    exe = shutil.which("component_container", path=libexec)
    assert exe is not None, f"no executable component_container in {libexec}"


def test_ros2_component_types_lists_exactly_the_products_components(ament_prefix):
    from ament_index_python import get_resource, get_resources

    assert "cloneguard" in get_resources("rclcpp_components")
    content, base = get_resource("rclcpp_components", "cloneguard")
    lines = content.splitlines()
    assert [line.split(";")[0] for line in lines] == _product_component_types()
    for line in lines:
        # What an rclcpp container would dlopen: a file that is plainly not
        # a shared library and says so (no ELF header, an explanation).
        library = Path(base) / line.split(";")[1]
        assert library.is_file(), library
        assert library.read_bytes()[:4] != b"\x7fELF"
        assert "not a shared library" in library.read_text()


def test_the_executable_launch_resolves_runs_an_isolated_container(ament_prefix, container_factory):
    from ament_index_python.packages import get_package_prefix

    exe = shutil.which("component_container", path=os.path.join(get_package_prefix("cloneguard"), "lib", "cloneguard"))
    # As ComposableNodeContainer(name='my_container', …, arguments=['--isolated']) runs it.
    container = container_factory.start(["--isolated"], node_name="my_container", exe=exe)
    client = container_factory.connect(container)
    for component in _product_component_types():
        client.load_ok("cloneguard", component, node_name=component.split("::")[1].lower())
    assert [name for _, name in client.list()] == ["/talker", "/listener", "/echoservice", "/heartbeat"]
    # The wrapper exec'd the container: the pid launch started (and will
    # signal on shutdown) is the container's own, not a shell in between.
    assert "python" in os.path.basename(os.readlink(f"/proc/{container.pid}/exe"))
    # launch ends its processes with SIGINT to that pid first.
    container.signal(signal.SIGINT)
    assert container.wait(timeout=10) == 0
