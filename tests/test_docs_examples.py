"""The code examples of the documentation run as written."""

from __future__ import annotations

import re

from cloneguard.harness.process import REPO_ROOT


def _python_blocks(path) -> list[str]:
    return re.findall(r"```python\n(.*?)```", path.read_text(), re.S)


def test_the_component_authors_repair_callback_example_runs():
    [example] = _python_blocks(REPO_ROOT / "docs" / "component-authors.md")
    ns: dict = {}
    exec(compile(example, "component-authors.md", "exec"), ns)
    ns["set_calibration"](0.5, 2.0)
    assert ns["CALIB"] == {"offset": 0.5, "scale": 2.0}
    ns["_calib_reset"](None)
    assert ns["CALIB"] == {"offset": 0.0, "scale": 1.0}
    from cloneguard.container import locks

    assert locks._callbacks[ns["CALIB_LOCK"]] is ns["_calib_reset"]
