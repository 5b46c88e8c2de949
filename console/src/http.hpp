#pragma once
// cpp-httplib, after Eigen: httplib.h includes <resolv.h>, whose `_res` macro breaks Eigen's
// headers when they come after it (Eigen names a parameter `_res`).
// clang-format off
#include <Eigen/Core>
#include <httplib.h>
// clang-format on
