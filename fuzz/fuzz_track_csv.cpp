// libFuzzer: the track CSV and deformation CSV readers (record/track_csv), which `pulsetrack
// analyze` and `evaluate` run on files people edit by hand. Input: the file; the first byte
// picks the reader.

#include "fuzz_file.hpp"
#include "pulsetrack/record/track_csv.hpp"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  if (size == 0) return 0;
  using namespace pulsetrack;
  const bool deformation = (data[0] & 1) != 0;
  const auto path =
      fuzz::writeInput(deformation ? "deformation.csv" : "track.csv", data + 1, size - 1);
  if (deformation) {
    if (auto rows = record::readDeformationCsv(path); !rows)
      fuzz::requireNamed(rows.error().message, path);
  } else {
    if (auto rows = record::readTrackCsv(path); !rows)
      fuzz::requireNamed(rows.error().message, path);
  }
  return 0;
}
