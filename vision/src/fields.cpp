#include "pulsetrack/vision/fields.hpp"

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <opencv2/core.hpp>

namespace pulsetrack::vision {

void fieldImage(const cv::Mat& frame, int parity, cv::Mat& out) {
  CV_Assert(frame.type() == CV_8UC1 && frame.rows >= 4 && (parity == 0 || parity == 1));
  out.create(frame.size(), CV_8UC1);
  const int rows = frame.rows, cols = frame.cols;
  // The field's own row nearest to y in direction `step` (+-1, +-3 rows): clamped to the field.
  const auto own = [&](int y) {
    // Rows of this parity only, inside the image.
    const int first = parity, last = (rows - 1 - parity) % 2 == 0 ? rows - 1 : rows - 2;
    return frame.ptr<uint8_t>(std::clamp(y, first, last));
  };
  for (int y = 0; y < rows; ++y) {
    uint8_t* dst = out.ptr<uint8_t>(y);
    if ((y & 1) == parity) {
      std::copy_n(frame.ptr<uint8_t>(y), cols, dst);
      continue;
    }
    const uint8_t* a = own(y - 3);
    const uint8_t* b = own(y - 1);
    const uint8_t* c = own(y + 1);
    const uint8_t* d = own(y + 3);
    for (int x = 0; x < cols; ++x) {
      const int v = 9 * (b[x] + c[x]) - a[x] - d[x];
      dst[x] = static_cast<uint8_t>(std::clamp((v + 8) >> 4, 0, 255));
    }
  }
}

void splitFields(const cv::Mat& frame, FieldOrder order, cv::Mat& first, cv::Mat& second) {
  const int top = order == FieldOrder::kTopFirst ? 0 : 1;
  fieldImage(frame, top, first);
  fieldImage(frame, 1 - top, second);
}

}  // namespace pulsetrack::vision
