"""The warning flags every C build of the project uses (setup.py, the cffi
builders of the product and of the test rig): one list, read by each.

-Wshadow: a local that hides another name (a global, an outer local) is a
second meaning of one name. -Wmissing-prototypes: a function with external
linkage defined with no declaration before it, i.e. one no header offers
(make it static, or declare it in the header of what its file offers)."""

# The C++ of setup.py (dds_defaults.cpp, pybind11_registry.cpp) keeps the
# common set: g++ has no -Wmissing-prototypes, and -Wshadow fires there in
# pybind11's and Fast DDS's own headers.
CXX_WARNINGS = ["-Wall", "-Wextra", "-Werror"]
WARNINGS = [*CXX_WARNINGS, "-Wshadow", "-Wmissing-prototypes"]


def cffi_init_prototype(module: str) -> str:
    """The line a cffi builder ends its set_source text with: the unit cffi
    generates defines ``PyInit_<name>`` without declaring it first, which
    -Wmissing-prototypes refuses (module: the dotted name given cffi)."""
    return f"PyMODINIT_FUNC PyInit_{module.rpartition('.')[2]}(void);\n"
