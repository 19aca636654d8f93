"""Thread mode needs no clone core.

Where isolated mode's C cannot be built (setup.py builds it optionally) the
container still serves in thread mode, intra-process messaging included, and
``--isolated`` refuses with the reason. Simulated here by a container whose
interpreter cannot import ``container.isolated._clonecore``.
"""

import sys

import pytest
from std_msgs.msg import String

from cloneguard.harness.factory import ContainerFactory

WITHOUT_CORE = f"""#!{sys.executable}
import sys
sys.modules["cloneguard.container.isolated._clonecore"] = None   # import fails: not built here
from cloneguard.container.cli import main
sys.exit(main())
"""


@pytest.fixture
def factory(domain_id, tmp_path, _leftovers):
    """Containers of the executable above (checked for leftovers like any)."""
    exe = tmp_path / "component_container_without_core"
    exe.write_text(WITHOUT_CORE)
    exe.chmod(0o755)
    made = ContainerFactory(domain_id, tmp_path, exe=str(exe))
    _leftovers.factories.append(made)
    yield made
    made.stop_all()


def test_thread_mode_serves_without_the_clone_core(factory):
    container = factory.start([])
    client = factory.connect(container)
    intra = {"use_intra_process_comms": True}
    client.load_ok("cloneguard", "cloneguard::Listener", extra_arguments=intra)
    talker = client.load_ok("cloneguard", "cloneguard::Talker", parameters={"period": 0.01}, extra_arguments=intra)
    heard = client.subscribe(String, "/chatter")
    heard.wait_count(3, timeout=10)
    assert client.unload(talker.unique_id).success
    assert [name for _, name in client.list()] == ["/listener"]
    assert "_clonecore" not in open(f"/proc/{container.pid}/maps").read()


def test_isolated_mode_refuses_without_the_clone_core(factory):
    proc = factory.start(["--isolated"])
    assert proc.wait(timeout=30) == 1
    assert "--isolated is unavailable here: C core not built" in proc.log_text()
