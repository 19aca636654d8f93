"""cffi (API mode) builder for container._rclglue: the container's calls into rcl
(node and service set-up and teardown, serialized takes) and intra/'s wakers.

The C is rclglue.c (the generated module #includes it, so compiler messages
point at rclglue.c lines) and waker.c (a second source), both in rclglue/; rclglue.h and
waker.h are their interfaces, whose cdef blocks are the module's cdef
(scripts/cdef.py), after what it assumes of rcl's types.

It is compiled against the real rcl/rmw/rcutils headers of the ROS 2 Jazzy
wheels in this venv (``<sys.prefix>/include/<pkg>/<pkg>/...``) and linked to
the same librcl/librmw/librcutils that rclpy loads (``<sys.prefix>/lib``).
sys.prefix is the venv of the interpreter that builds (pip runs setup.py
with it), so a fresh clone's venv builds against its own wheels.

How the libraries are found at run time: rclpy's own extension carries an
RPATH into a ``ros_rclpy.libs`` directory that is not where the wheels put
things; it works because the ``ros_wheels_bootstrapper`` .pth re-executes
every interpreter of the venv with LD_LIBRARY_PATH = ``<venv>/lib`` plus the
``site-packages/ros_*.libs`` directories (the vendored libyaml, lttng, ... of
librcl).  We do not rely on that for our direct dependencies: the module gets
a run path to ``<venv>/lib`` (absolute, fixed at build time: rebuild if the
venv moves).  librcl's own dependencies still come through LD_LIBRARY_PATH,
as for rclpy; in practice rclpy (imported first by dds_reader) has loaded
them all already, and the loader reuses an already loaded librcl.so by its
soname, so there is one librcl in the process, shared with rclpy.

Built by setup.py (``cffi_modules``); after an edit of the C,
``pip install --no-build-isolation --no-deps -e .`` rebuilds it in place.
"""

import runpy
import sys
from pathlib import Path

from cffi import FFI

# The project's C warning flags: one list for every build (scripts/cflags.py).
CFLAGS = runpy.run_path(str(Path(__file__).resolve().parents[1] / "scripts" / "cflags.py"))
WARNINGS = CFLAGS["WARNINGS"]

HERE = Path(__file__).resolve().parent

PREFIX = Path(sys.prefix)
LIB_DIR = PREFIX / "lib"

# The packages whose headers rcl/subscription.h and rcl/publisher.h pull in
# (directly or through rcl/node.h, rcl/arguments.h, rcl/time.h, ...).  Each
# wheel installs its headers as include/<pkg>/<pkg>/*.h, so every package is
# one include directory.
HEADER_PACKAGES = (
    "rcl",
    "rmw",
    "rcutils",
    "rcl_yaml_param_parser",
    "rosidl_runtime_c",
    "rosidl_typesupport_interface",
    "rosidl_dynamic_typesupport",
    "type_description_interfaces",
    "service_msgs",
    "builtin_interfaces",
    # ComponentEvent's C struct, for the herald's event (rosidl's, generated
    # from the .msg by scripts/build_interfaces.py before this is built).
    "cloneguard_interfaces",
)


def _include_dirs() -> list[str]:
    dirs: list[str] = []
    missing: list[str] = []
    for pkg in HEADER_PACKAGES:
        d = PREFIX / "include" / pkg
        (dirs if (d / pkg).is_dir() else missing).append(str(d))
    if missing:
        raise RuntimeError(
            f"ROS 2 headers not found in {PREFIX} ({', '.join(missing)}): build "
            "cloneguard.container._rclglue with the venv's python after "
            "`pip install -r scripts/requirements.txt`"
        )
    return dirs


# rcl's types as far as Python uses them (opaque, but for the serialized
# message's buffer: rcutils_uint8_array_t's fields) ...
RCL_TYPES = r"""
typedef struct { ...; } rcl_publisher_t;
typedef struct { ...; } rcl_subscription_t;
typedef struct { ...; } rcl_service_t;
typedef struct { ...; } rcl_node_t;
typedef struct { ...; } rcl_context_t;
typedef struct {
    uint8_t *buffer;
    size_t buffer_length;
    size_t buffer_capacity;
    ...;
} rcl_serialized_message_t;
"""
# ... and ours, each written once, in the headers' cdef blocks (scripts/cdef.py).
GLUE = HERE / "rclglue"  # the folder of this module's C
HEADERS = (GLUE / "rclglue.h", GLUE / "waker.h")
CDEF = RCL_TYPES + runpy.run_path(str(HERE.parent / "scripts" / "cdef.py"))["cdef"](HEADERS)

ffibuilder = FFI()
ffibuilder.cdef(CDEF)
ffibuilder.set_source(
    "cloneguard.container._rclglue",
    '#include "rclglue.c"\n#include "waker.h"\n' + CFLAGS["cffi_init_prototype"]("cloneguard.container._rclglue"),
    sources=["container/rclglue/waker.c"],
    include_dirs=[str(GLUE), *_include_dirs()],
    # setuptools wants paths relative to the repo root (where setup.py runs).
    depends=[
        "container/rclglue/rclglue.c",
        "container/rclglue/rclglue.h",
        "container/rclglue/waker.c",
        "container/rclglue/waker.h",
        "scripts/cdef.py",
    ],
    libraries=["rcl", "rmw", "rcutils"],
    library_dirs=[str(LIB_DIR)],
    extra_compile_args=["-std=gnu11", *WARNINGS],
    extra_link_args=[f"-Wl,-rpath,{LIB_DIR}"],
    # Tied to CPython 3.11 by the ROS wheels anyway. Not abi3, so that every
    # build produces _rclglue.cpython-311-*.so: an abi3 file would be
    # shadowed by a stale cpython-311 one.
    py_limited_api=False,
)
