// HDF5 string lists and matrices (see h5_arrays.h).
#include "eval/h5_arrays.h"

namespace mc {

void write_strings(H5::Group& g, const std::string& name, const std::vector<std::string>& v) {
  H5::StrType type(H5::PredType::C_S1, H5T_VARIABLE);
  type.setCset(H5T_CSET_UTF8);
  hsize_t n = v.size();
  H5::DataSpace space(1, &n);
  std::vector<const char*> ptrs;
  for (auto& x : v) ptrs.push_back(x.c_str());
  auto ds = g.createDataSet(name, type, space);
  if (n > 0) ds.write(ptrs.data(), type);
}

std::vector<std::string> read_strings(H5::Group& g, const std::string& name) {
  H5::DataSet ds = g.openDataSet(name);
  hsize_t n = 0;
  // A damaged (unsealed) file may hold more dimensions than the one n has room for.
  if (ds.getSpace().getSimpleExtentNdims() != 1) throw H5::DataSetIException("read_strings", name + " is not 1-D");
  ds.getSpace().getSimpleExtentDims(&n);
  H5::StrType type(H5::PredType::C_S1, H5T_VARIABLE);
  type.setCset(H5T_CSET_UTF8);  // as written: HDF5 does not convert between character sets
  std::vector<char*> ptrs(n, nullptr);
  if (n > 0) ds.read(ptrs.data(), type);
  std::vector<std::string> out;
  for (char* c : ptrs) out.emplace_back(c ? c : ""), H5free_memory(c);
  return out;
}

void write_matrix(H5::Group& g, const std::string& name, const Eigen::MatrixXd& m) {
  hsize_t dims[2] = {static_cast<hsize_t>(m.rows()), static_cast<hsize_t>(m.cols())};
  H5::DataSpace space(2, dims);
  Eigen::Matrix<double, Eigen::Dynamic, Eigen::Dynamic, Eigen::RowMajor> rm = m;
  g.createDataSet(name, H5::PredType::IEEE_F64LE, space).write(rm.data(), H5::PredType::NATIVE_DOUBLE);
}

Eigen::MatrixXd read_matrix(H5::Group& g, const std::string& name) {
  H5::DataSet ds = g.openDataSet(name);
  hsize_t dims[2] = {0, 0};
  if (ds.getSpace().getSimpleExtentNdims() != 2) throw H5::DataSetIException("read_matrix", name + " is not 2-D");
  ds.getSpace().getSimpleExtentDims(dims);
  Eigen::Matrix<double, Eigen::Dynamic, Eigen::Dynamic, Eigen::RowMajor> rm(dims[0], dims[1]);
  if (dims[0] * dims[1] > 0) ds.read(rm.data(), H5::PredType::NATIVE_DOUBLE);
  return rm;
}

}  // namespace mc
