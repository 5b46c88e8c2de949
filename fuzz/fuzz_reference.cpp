// libFuzzer: the reference-tracker inputs of `pulsetrack validate` (analysis/reference): NDI
// pose exports or matrices, the digitized divots, the protocol log. The first byte picks the
// reader; the rest is the file.

#include "fuzz_file.hpp"
#include "pulsetrack/analysis/reference.hpp"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  if (size == 0) return 0;
  using namespace pulsetrack;
  const auto path = fuzz::writeInput("reference.csv", data + 1, size - 1);
  switch (data[0] % 4) {
    case 0:
      if (auto t = analysis::readCsv(path); !t) fuzz::requireNamed(t.error().message, path);
      break;
    case 1:
      if (auto p = analysis::readPoses(path); !p) fuzz::requireNamed(p.error().message, path);
      break;
    case 2:
      if (auto d = analysis::readDivots(path); !d) fuzz::requireNamed(d.error().message, path);
      break;
    default:
      if (auto a = analysis::readProtocol(path); !a) fuzz::requireNamed(a.error().message, path);
      break;
  }
  return 0;
}
