// pybind11's registry of live instances, kept ahead of the node processes.
//
// Why: every pybind11 module of one interpreter (rclpy's _rclpy_pybind11
// and any a component brings) shares one `internals` struct, and in it
// `registered_instances`, a std::unordered_multimap from C++ pointer to
// Python instance: an instance is inserted when made (rclpy makes a WaitSet
// on every spin) and erased when freed. An insert that outgrows the bucket
// array rehashes: libstdc++ unlinks every node and relinks it into a new
// array, one at a time. A node process killed (SIGKILL from outside,
// holding the GIL) in that loop leaves nodes reachable from nowhere; the
// next free of one of those instances finds it unregistered and pybind11
// calls std::terminate: the whole container dies (deep-12-outside, trial
// 882). An insert that does not rehash writes two or three pointers.
//
// So the container rehashes, on its own threads, before any node process
// must: `keep_ahead` reserves buckets whenever fewer than `headroom`
// inserts remain before the next rehash. Node processes then only insert
// and erase.
//
// What this rests on (pybind11_registry.py checks it at start-up): this
// file is built against pybind11 3.0.x headers, whose internals ABI
// (PYBIND11_INTERNALS_VERSION 11, this compiler's platform ABI id) is
// rclpy's: then get_internals() returns the struct rclpy's modules use,
// found under the same key in the interpreter's state dict. The check: the
// registry this module sees holds rclpy's own types. Every call holds the
// GIL (pybind11's lock for its internals in a build with a GIL).
#include <pybind11/pybind11.h>

#include <cmath>

namespace py = pybind11;
namespace detail = pybind11::detail;

#ifdef Py_GIL_DISABLED
#error "a free-threaded CPython shards registered_instances; not handled"
#endif

namespace
{

// Inserts left before the next one rehashes (libstdc++ rehashes when the
// element count would pass bucket_count * max_load_factor).
long inserts_left(const detail::instance_map &map)
{
    const double capacity =
        std::floor(static_cast<double>(map.bucket_count()) * map.max_load_factor());
    return static_cast<long>(capacity) - static_cast<long>(map.size());
}

} // namespace

PYBIND11_MODULE(_pybind11_registry, m)
{
    m.doc() = "pybind11's registry of live instances, kept ahead of the node processes";
    m.attr("INTERNALS_ID") = PYBIND11_INTERNALS_ID;

    m.def(
        "knows_type",
        [](py::handle type) {
            if (!PyType_Check(type.ptr()))
                throw py::type_error("knows_type: a type is needed");
            return detail::get_type_info(reinterpret_cast<PyTypeObject *>(type.ptr())) != nullptr;
        },
        "Is this pybind11 type registered in the internals this module shares?");

    m.def(
        "state",
        []() {
            const auto &map = detail::get_internals().registered_instances;
            return py::make_tuple(map.size(), map.bucket_count(), inserts_left(map));
        },
        "(instances, buckets, inserts left before a rehash)");

    m.def(
        "keep_ahead",
        [](long headroom) {
            if (headroom <= 0)
                throw py::value_error("keep_ahead: headroom must be positive");
            auto &map = detail::get_internals().registered_instances;
            if (inserts_left(map) >= headroom)
                return false;
            // Twice what is needed now: rehashes stay rare as the map grows.
            map.reserve(2 * (map.size() + static_cast<size_t>(headroom)));
            return true;
        },
        py::arg("headroom"),
        "Rehash now unless `headroom` inserts are left before the next rehash; True if it "
        "rehashed.");
}
