// HDF5 columns shared by the evaluation files (metrics.h5) and the replay's
// per-sample records (samples.h5): UTF-8 string lists and row-major matrices
// (numpy's order: sample i is row i).
#pragma once
#include <H5Cpp.h>

#include <Eigen/Dense>
#include <string>
#include <vector>

namespace mc {

void write_strings(H5::Group& g, const std::string& name, const std::vector<std::string>& v);
// Throws H5::DataSetIException when the dataset is not 1-D.
std::vector<std::string> read_strings(H5::Group& g, const std::string& name);
void write_matrix(H5::Group& g, const std::string& name, const Eigen::MatrixXd& m);
// Throws H5::DataSetIException when the dataset is not 2-D (callers turn it into a
// UserError naming the file).
Eigen::MatrixXd read_matrix(H5::Group& g, const std::string& name);

}  // namespace mc
