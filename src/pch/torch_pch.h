// Precompiled header for every torch translation unit (saves ~14 s per file).
#pragma once
#include <torch/torch.h>
#include <fmt/format.h>
#include <Eigen/Dense>
#include <string>
#include <vector>
#include <memory>
#include <map>
