// libFuzzer: the recording reader (record::Reader) on a frames.ptv it did not write: headers,
// records, CRCs, zstd frames. The manifest and rig of the folder are fixed and valid (a 16x12
// recording); the input is frames.ptv. Every frame the reader indexed is read and decoded. The
// first input byte picks the manifest.toml variant instead when it is 'M' (the rest is the
// manifest's text), so the manifest parser is fuzzed by the same harness.

#include "fuzz_file.hpp"
#include "pulsetrack/record/recording.hpp"

namespace {

namespace fs = std::filesystem;

const char* kManifest =
    "format = \"pulsetrack-recording\"\nversion = 1\nsource = \"fuzz\"\nrig_id = \"fuzz\"\n"
    "width = 16\nheight = 12\npixel_format = \"gray8\"\nnominal_fps = 10\n"
    "created = \"2026-12-02T00:00:00Z\"\n";

const char* kRig =
    "%YAML:1.0\n---\nimage_size: [ 16, 12 ]\n"
    "M1: !!opencv-matrix\n   rows: 3\n   cols: 3\n   dt: d\n   data: [ 20., 0., 8., 0., 20., 6., "
    "0., 0., 1. ]\n"
    "D1: !!opencv-matrix\n   rows: 1\n   cols: 5\n   dt: d\n   data: [ 0., 0., 0., 0., 0. ]\n"
    "M2: !!opencv-matrix\n   rows: 3\n   cols: 3\n   dt: d\n   data: [ 20., 0., 8., 0., 20., 6., "
    "0., 0., 1. ]\n"
    "D2: !!opencv-matrix\n   rows: 1\n   cols: 5\n   dt: d\n   data: [ 0., 0., 0., 0., 0. ]\n"
    "R: !!opencv-matrix\n   rows: 3\n   cols: 3\n   dt: d\n   data: [ 1., 0., 0., 0., 1., 0., 0., "
    "0., 1. ]\n"
    "T: !!opencv-matrix\n   rows: 3\n   cols: 1\n   dt: d\n   data: [ -60., 0., 0. ]\n"
    "rms: 0.1\n";

const fs::path& folder() {
  static const fs::path dir = [] {
    fs::path d = pulsetrack::fuzz::scratchDir() / "recording";
    fs::create_directories(d);
    std::ofstream(d / "rig.yaml") << kRig;
    return d;
  }();
  return dir;
}

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  const fs::path& dir = folder();
  if (size > 0 && data[0] == 'M') {
    pulsetrack::fuzz::writeFile(dir / "manifest.toml", data + 1, size - 1);
    pulsetrack::fuzz::writeFile(dir / "frames.ptv", nullptr, 0);
  } else {
    std::ofstream(dir / "manifest.toml", std::ios::trunc) << kManifest;
    pulsetrack::fuzz::writeFile(dir / "frames.ptv", data, size);
  }
  auto reader = pulsetrack::record::Reader::open(dir);
  if (!reader) {
    pulsetrack::fuzz::requireNamed(reader.error().message, dir);
    return 0;
  }
  cv::Mat left, right;
  for (size_t i = 0; i < reader->size(); ++i) {
    if (auto ok = reader->read(i, left, right); ok) {
      if (left.cols != 16 || left.rows != 12 || right.cols != 16 || right.rows != 12)
        __builtin_trap();
    }
  }
  return 0;
}
