"""The harness's own exception, in a module that imports nothing of ROS.

The pytest plugin needs it at start-up, before any fixture has set the ROS
environment (rcl ends the process at its first import when the environment
names an RMW that is not installed)."""


class HarnessTimeout(AssertionError):
    """Something the harness waited for did not happen in time."""
