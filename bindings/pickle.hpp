// Pickled states of result objects (what multiprocessing, Dask and joblib send between processes,
// and what copy.deepcopy uses): a dict by field name for plain structs, helpers for the others.
#pragma once

#include <pybind11/numpy.h>
#include <pybind11/pybind11.h>

#include <string>
#include <type_traits>
#include <vector>

namespace terracube::python {

namespace py = pybind11;

/// py::pickle for a plain struct T whose fields `fields(r, f)` lists, calling f(name, field) for
/// each (name: the Python attribute's; a generic lambda serves both the const and the mutable
/// struct). The state is a dict by name; a state missing a field or holding one more is refused
/// with ValueError naming the type.
template <typename T, typename Fields>
auto pickle_by_fields(const char* type, Fields fields) {
  return py::pickle(
      [fields](const T& r) {
        py::dict state;
        fields(r, [&](const char* name, const auto& field) { state[name] = field; });
        return state;
      },
      [fields, type](const py::dict& state) {
        T r;
        std::size_t count = 0;
        fields(r, [&](const char* name, auto& field) {
          if (!state.contains(name)) throw py::value_error(std::string(type) + ": the pickled state has no " + name);
          field = state[name].template cast<std::decay_t<decltype(field)>>();
          ++count;
        });
        if (state.size() != count) throw py::value_error(std::string(type) + ": the pickled state has unknown fields");
        return r;
      });
}

/// The values of the 1-D array `item` of a pickled state; ValueError naming `what` otherwise.
template <typename T>
std::vector<T> vector_of(const py::handle& item, const char* what) {
  const auto array = py::array_t<T, py::array::c_style | py::array::forcecast>::ensure(item);
  if (!array || array.ndim() != 1) throw py::value_error(std::string(what) + " must be a 1-D array");
  return std::vector<T>(array.data(), array.data() + array.size());
}

/// The items of a pickled state, checked for their number; ValueError naming the class otherwise.
inline py::tuple state_items(const py::tuple& state, std::size_t count, const char* type) {
  if (state.size() != count) {
    throw py::value_error(std::string(type) + ": a pickled state has " + std::to_string(count) + " items, got " +
                          std::to_string(state.size()));
  }
  return state;
}

}  // namespace terracube::python
