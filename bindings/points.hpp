// Numpy (N, 3) arrays (or wider rows, x, y, z first) to terracube::PointsView without copies.
#pragma once

#include <pybind11/numpy.h>
#include <pybind11/pybind11.h>
#include <terracube/cube_grid.hpp>

#include <string>
#include <vector>

namespace terracube::python {

namespace py = pybind11;

inline std::string shape_string(const py::array& array) {
  std::string text = "(";
  for (py::ssize_t axis = 0; axis < array.ndim(); ++axis) {
    text += std::to_string(array.shape(axis)) + (array.ndim() == 1 || axis + 1 < array.ndim() ? "," : "");
    if (axis + 1 < array.ndim()) text += " ";
  }
  return text + ")";
}

/// The widest rows taken, x, y, z first (intensity, ring, time, colour, normals ...): wider arrays
/// are more likely a transposed cloud, (3, N), than points.
constexpr py::ssize_t kMaxPointColumns = 16;

/// Calls f(PointsView<float>) or f(PointsView<double>) on an (N, 3) float32/float64 array of
/// any strides, or the x, y, z of wider rows (up to kMaxPointColumns columns, x, y, z first),
/// without copying. Raises ValueError for a wrong shape, TypeError for a wrong dtype.
template <typename F>
auto with_points(const py::array& array, const char* name, F&& f) {
  if (array.ndim() != 2 || array.shape(1) < 3 || array.shape(1) > kMaxPointColumns) {
    const bool transposed = array.ndim() == 2 && array.shape(0) >= 3 && array.shape(0) <= kMaxPointColumns &&
                            array.shape(1) > kMaxPointColumns;
    throw py::value_error(std::string(name) + " must be an (N, 3) array of x, y, z (or rows of up to " +
                          std::to_string(kMaxPointColumns) + " values, x, y, z first), got shape " +
                          shape_string(array) +
                          (transposed ? ": a cloud stored by columns? pass its transpose, .T" : ""));
  }
  const auto view = [&](auto scalar) {
    using Scalar = decltype(scalar);
    const auto item = static_cast<py::ssize_t>(sizeof(Scalar));
    if (array.strides(0) % item != 0 || array.strides(1) % item != 0) {
      // Misaligned strides (rare: a view into a packed structured array) take one copy.
      const auto copy = py::array_t<Scalar, py::array::c_style | py::array::forcecast>::ensure(array);
      return f(PointsView<Scalar>(copy.data(), static_cast<std::size_t>(copy.shape(0)), copy.shape(1), 1));
    }
    return f(PointsView<Scalar>(static_cast<const Scalar*>(array.data()), static_cast<std::size_t>(array.shape(0)),
                                array.strides(0) / item, array.strides(1) / item));
  };
  if (py::isinstance<py::array_t<float>>(array)) return view(float{});
  if (py::isinstance<py::array_t<double>>(array)) return view(double{});
  throw py::type_error(std::string(name) + " must be float32 or float64, got dtype " +
                       py::str(array.dtype()).cast<std::string>() + "; convert with .astype(numpy.float64)");
}

/// A view of an optional (M, 3) array of directions: none for None; float64 of any strides
/// viewed as it is, anything else converted once into `keep` (which must outlive the view).
/// Raises ValueError for another shape.
inline PointsView<double> directions_view(const py::object& directions, const char* name, py::object& keep) {
  if (directions.is_none()) return {};
  auto array = py::array_t<double, py::array::forcecast>::ensure(directions);
  if (!array || array.ndim() != 2 || array.shape(1) != 3) {
    throw py::value_error(std::string(name) + " must be an (M, 3) array of directions");
  }
  if (array.strides(0) % 8 != 0 || array.strides(1) % 8 != 0) {
    array = py::array_t<double, py::array::c_style | py::array::forcecast>::ensure(array);
  }
  keep = array;
  return {array.data(), static_cast<std::size_t>(array.shape(0)), array.strides(0) / 8, array.strides(1) / 8};
}

inline py::array read_only(py::array array) {
  array.attr("setflags")(py::arg("write") = false);
  return array;
}

/// A read-only numpy array viewing `data` that keeps `owner` (the C++ result object) alive.
template <typename T>
py::array view_of(const std::vector<T>& data, const py::object& owner) {
  return read_only(py::array_t<T>({static_cast<py::ssize_t>(data.size())}, {static_cast<py::ssize_t>(sizeof(T))},
                                  data.data(), owner));
}

/// A numpy bool array viewing a vector of 0/1 bytes, keeping `owner` alive; read-only when the
/// owner is a result object that other views share.
inline py::array bool_view_of(const std::vector<std::uint8_t>& data, const py::object& owner, bool writeable = false) {
  py::array array(py::dtype("bool"), {static_cast<py::ssize_t>(data.size())}, {py::ssize_t{1}}, data.data(), owner);
  return writeable ? array : read_only(array);
}

}  // namespace terracube::python
