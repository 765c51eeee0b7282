#include <pybind11/pybind11.h>
namespace py = pybind11;
namespace terracube::python {
void bind_mapper(py::module_& m) { (void)m; }
}  // namespace terracube::python
