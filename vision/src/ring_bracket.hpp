#pragma once
// A time-ordered ring (capacity times.size(), oldest at `head`, `size` entries): the two slots
// around time t and the weight of the later one, for linear interpolation. Shared by the motion
// predictor's history of the signal and the deformation field's history of its solutions.

#include <cstddef>
#include <vector>

namespace pulsetrack::vision {

// False when t is outside [oldest, newest] (1e-12 s of slack). Else value(t) =
// (1 - f) value[a] + f value[b]; an exact hit gives a == b, f == 0.
inline bool ringBracket(const std::vector<double>& times, size_t head, size_t size, double t,
                        size_t& a, size_t& b, double& f) noexcept {
  if (size == 0) return false;
  const size_t cap = times.size();
  const auto idx = [&](size_t i) { return (head + i) % cap; };  // the i-th oldest
  if (t < times[idx(0)] - 1e-12 || t > times[idx(size - 1)] + 1e-12) return false;
  size_t lo = 0, hi = size - 1;  // the first with time >= t
  while (lo < hi) {
    const size_t mid = (lo + hi) / 2;
    if (times[idx(mid)] < t)
      lo = mid + 1;
    else
      hi = mid;
  }
  b = idx(lo);
  if (lo == 0 || times[b] <= t) {
    a = b;
    f = 0.0;
    return true;
  }
  a = idx(lo - 1);
  f = (t - times[a]) / (times[b] - times[a]);
  return true;
}

}  // namespace pulsetrack::vision
