"""The warning flags every C build of the project uses (setup.py, the cffi
builders of the product and of the test rig): one list, read by each."""

WARNINGS = ["-Wall", "-Wextra", "-Werror"]
