// The recording format: exact round trip, a file cut anywhere reads back to its last complete
// frame, corruption and version mismatches are named.

#include "pulsetrack/record/recording.hpp"

#include <gmock/gmock.h>
#include <gtest/gtest.h>
#include <signal.h>
#include <sys/resource.h>
#include <sys/wait.h>
#include <unistd.h>
#include <zlib.h>

#include <atomic>
#include <cstring>
#include <fstream>
#include <limits>
#include <opencv2/calib3d.hpp>
#include <random>
#include <thread>

#include "pulsetrack/record/live_recorder.hpp"
#include "pulsetrack/record/track_csv.hpp"
#include "test_util.hpp"

namespace pulsetrack::record {
namespace {

vision::StereoRig smallRig(cv::Size size) {
  vision::StereoRig rig;
  const double d[5] = {-0.1, 0.05, 0, 0, 0};
  rig.left = vision::CameraModel({800, 0, size.width / 2.0, 0, 800, size.height / 2.0, 0, 0, 1}, d,
                                 5, size);
  rig.right = rig.left;
  rig.t = {-60, 0, 0};
  return rig;
}

Manifest manifest(cv::Size size) {
  Manifest m;
  m.source = "test";
  m.rig_id = "bench-rig";
  m.width = size.width;
  m.height = size.height;
  m.nominal_fps = 10;
  return m;
}

cv::Mat noiseImage(cv::Size size, int seed) {
  cv::Mat img(size, CV_8UC1);
  cv::RNG rng(static_cast<uint64>(seed));
  rng.fill(img, cv::RNG::NORMAL, 128, 20);
  return img;
}

class Recording : public ::testing::TestWithParam<int> {
 protected:
  test::TempDir tmp;
  const cv::Size size{160, 120};
  std::vector<std::pair<cv::Mat, cv::Mat>> frames;
  std::filesystem::path dir = tmp.path() / "rec";

  void record(int n, int level) {
    auto w = Writer::create(dir, manifest(size), smallRig(size), level);
    ASSERT_TRUE(w) << w.error().message;
    for (int i = 0; i < n; ++i) {
      frames.emplace_back(noiseImage(size, 2 * i), noiseImage(size, 2 * i + 1));
      // Frame 3 dropped: the index and timestamps jump.
      const uint64_t f = static_cast<uint64_t>(i < 3 ? i : i + 1);
      const FrameMeta meta{f, 1000 + f, static_cast<int64_t>(f) * 100'000'000,
                           static_cast<int64_t>(f) * 100'000'000 + 20'000, 0};
      ASSERT_TRUE(w->write(meta, frames.back().first, frames.back().second));
    }
    EXPECT_EQ(w->framesWritten(), static_cast<uint64_t>(n));
    ASSERT_TRUE(w->close());
  }
};

TEST_P(Recording, RoundTripIsBitExact) {
  record(8, GetParam());
  auto r = Reader::open(dir);
  ASSERT_TRUE(r) << r.error().message;
  EXPECT_FALSE(r->truncation());
  ASSERT_EQ(r->size(), 8U);
  EXPECT_EQ(r->manifest().rig_id, "bench-rig");
  EXPECT_EQ(r->manifest().width, 160);
  EXPECT_DOUBLE_EQ(r->rig().t[0], -60.0);
  cv::Mat l, rr;
  for (size_t i = 0; i < 8; ++i) {
    ASSERT_TRUE(r->read(i, l, rr));
    EXPECT_EQ(cv::norm(l, frames[i].first, cv::NORM_INF), 0.0);
    EXPECT_EQ(cv::norm(rr, frames[i].second, cv::NORM_INF), 0.0);
  }
  EXPECT_EQ(r->meta(3).frame, 4U);  // the gap
  EXPECT_EQ(r->meta(3).trigger_seq, 1004U);
  EXPECT_EQ(r->meta(3).t_right_ns, 400'020'000);
  // The per-frame table for people says the same.
  std::ifstream csv(dir / "frames.csv");
  std::string line;
  std::getline(csv, line);
  EXPECT_EQ(line, "frame,trigger_seq,t_left_ns,t_right_ns,flags");
  for (int i = 0; i < 4; ++i) std::getline(csv, line);
  EXPECT_EQ(line, "4,1004,400000000,400020000,0");
}

INSTANTIATE_TEST_SUITE_P(Codecs, Recording, ::testing::Values(0, 1, 3), [](const auto& param_info) {
  return "zstd_level_" + std::to_string(param_info.param);
});

TEST_F(Recording, CutAnywhereReadsToTheLastCompleteFrame) {
  record(5, 1);
  const auto ptv = dir / "frames.ptv";
  const auto full = std::filesystem::file_size(ptv);
  std::vector<char> bytes(full);
  std::ifstream(ptv, std::ios::binary).read(bytes.data(), static_cast<std::streamsize>(full));
  // Find the record boundaries from an intact read.
  std::mt19937 rng(5);
  for (int trial = 0; trial < 40; ++trial) {
    const size_t cut = 32 + rng() % (full - 32);
    std::ofstream(ptv, std::ios::binary | std::ios::trunc)
        .write(bytes.data(), static_cast<std::streamsize>(cut));
    auto r = Reader::open(dir);
    ASSERT_TRUE(r) << r.error().message;
    ASSERT_LT(r->size(), 5U) << "cut at " << cut;
    ASSERT_TRUE(r->truncation()) << "cut at " << cut;
    cv::Mat l, rr;
    for (size_t i = 0; i < r->size(); ++i) {
      ASSERT_TRUE(r->read(i, l, rr));
      EXPECT_EQ(cv::norm(l, frames[i].first, cv::NORM_INF), 0.0);
    }
  }
}

TEST_F(Recording, PowerCutThatLeftZerosIsDropped) {
  record(4, 1);
  const auto ptv = dir / "frames.ptv";
  // Overwrite the last 100 bytes with zeros: the length is on disk, the data is not.
  std::fstream f(ptv, std::ios::binary | std::ios::in | std::ios::out);
  f.seekp(-100, std::ios::end);
  const std::string zeros(100, '\0');
  f.write(zeros.data(), 100);
  f.close();
  auto r = Reader::open(dir);
  ASSERT_TRUE(r) << r.error().message;
  EXPECT_EQ(r->size(), 3U);
  ASSERT_TRUE(r->truncation());
  EXPECT_NE(r->truncation().value_or("").find("failed its CRC"), std::string::npos);
}

TEST_F(Recording, CorruptFrameInTheMiddleIsNamed) {
  record(4, 1);
  const auto ptv = dir / "frames.ptv";
  auto r0 = Reader::open(dir);
  ASSERT_TRUE(r0);
  std::fstream f(ptv, std::ios::binary | std::ios::in | std::ios::out);
  f.seekp(32 + 64 + 10);  // inside frame 0's payload
  f.put('\x5a');
  f.close();
  auto r = Reader::open(dir);
  ASSERT_TRUE(r);
  cv::Mat l, rr;
  auto bad = r->read(0, l, rr);
  ASSERT_FALSE(bad);
  EXPECT_NE(bad.error().message.find("frames.ptv: frame 0: payload CRC mismatch"),
            std::string::npos)
      << bad.error().message;
  EXPECT_TRUE(r->read(1, l, rr));
}

TEST_F(Recording, BadFoldersAndVersionsAreNamed) {
  auto none = Reader::open(tmp.path() / "missing");
  ASSERT_FALSE(none);
  EXPECT_NE(none.error().message.find("not a recording folder"), std::string::npos);
  record(2, 1);
  std::string text;
  {
    std::ifstream in(dir / "manifest.toml");
    text.assign(std::istreambuf_iterator<char>(in), {});
  }
  const auto write_manifest = [&](const std::string& t) {
    std::ofstream(dir / "manifest.toml") << t;
  };
  std::string v2 = text;
  v2.replace(v2.find("version = 1"), 11, "version = 2");
  write_manifest(v2);
  auto r = Reader::open(dir);
  ASSERT_FALSE(r);
  EXPECT_NE(r.error().message.find("manifest.toml:3: recording format version 2 is not one"),
            std::string::npos)
      << r.error().message;
  write_manifest("format = \"pulsetrack-recording\"\nversion = 1\nwidth = [\n");
  r = Reader::open(dir);
  ASSERT_FALSE(r);
  EXPECT_NE(r.error().message.find("manifest.toml:"), std::string::npos) << r.error().message;
  std::string wrong = text;
  wrong.replace(wrong.find("width = 160"), 11, "width = 161");
  write_manifest(wrong);
  r = Reader::open(dir);
  ASSERT_FALSE(r);
  EXPECT_NE(r.error().message.find("frames are 160x120 but manifest.toml says 161x120"),
            std::string::npos)
      << r.error().message;
  write_manifest(text);
  std::ofstream(dir / "frames.ptv", std::ios::trunc) << "JUNKJUNKJUNKJUNKJUNKJUNKJUNKJUNKJUNK";
  r = Reader::open(dir);
  ASSERT_FALSE(r);
  EXPECT_NE(r.error().message.find("not a pulsetrack frames file"), std::string::npos);
}

// Found by fuzzing (issue 15): each of these was read without a word and tracked with exit 0.
// The forged fields carry valid CRCs (zlib's crc32, computed here from the documented layout in
// docs/recording-format.md, not by the writer), so only the reader's own checks can catch them.
class ForgedRecording : public Recording {
 protected:
  std::string original, bytes;
  void SetUp() override {
    record(3, 0);
    std::ifstream in(dir / "frames.ptv", std::ios::binary);
    original.assign(std::istreambuf_iterator<char>(in), {});
    bytes = original;
  }
  void reset() { bytes = original; }
  template <class T>
  void put(size_t at, T v) {
    std::memcpy(bytes.data() + at, &v, sizeof v);
  }
  void reseal(size_t header_at, size_t crc_at) {
    const auto crc =
        static_cast<uint32_t>(crc32(0L, reinterpret_cast<const Bytef*>(bytes.data() + header_at),
                                    static_cast<uInt>(crc_at - header_at)));
    put(crc_at, crc);
  }
  // The k-th record's header offset (raw frames: 64 + 2 images each).
  size_t recordAt(size_t k) const { return 32 + k * (64 + 2 * size_t(size.area())); }
  void patchRecord(size_t k, size_t field, auto value) {
    put(recordAt(k) + field, value);
    reseal(recordAt(k), recordAt(k) + 60);
  }
  std::string openError() {
    std::ofstream(dir / "frames.ptv", std::ios::binary | std::ios::trunc) << bytes;
    auto r = Reader::open(dir);
    if (r) return "opened with " + std::to_string(r->size()) + " frames";
    return r.error().message;
  }
};

TEST_F(ForgedRecording, FileHeaderFieldsNoWriterMakesAreNamed) {
  put<uint32_t>(24, 1361);  // pixel format
  reseal(0, 28);
  EXPECT_THAT(openError(), ::testing::HasSubstr("frames.ptv: pixel format 1361 is not one"));
  put<uint32_t>(24, 1);
  put<uint32_t>(12, 0x7fffffff);  // header size
  reseal(0, 28);
  EXPECT_THAT(openError(), ::testing::HasSubstr("frames.ptv: file header size 2147483647"));
}

TEST_F(ForgedRecording, RecordFieldsNoWriterMakesAreNamedWithTheirByte) {
  patchRecord(1, 24, std::numeric_limits<int64_t>::min());
  EXPECT_THAT(openError(),
              ::testing::HasSubstr("frames.ptv: record at byte " + std::to_string(recordAt(1)) +
                                   " (frame 1): negative timestamp"));
  reset();
  patchRecord(1, 40, uint32_t{4});
  EXPECT_THAT(openError(), ::testing::HasSubstr("flags 0x4 are reserved"));
  reset();
  patchRecord(1, 44, uint32_t{7});
  EXPECT_THAT(openError(), ::testing::HasSubstr("codec 7 is not one"));
  // Untouched, it opens: the checks above are the forgeries', not the fixture's.
  reset();
  EXPECT_EQ(openError(), "opened with 3 frames");
}

// Out of order is a warning, not an error: a daemon recording across a camera reopen restarts
// its numbering (a wrapped index) and a looped replay recorded again repeats its stamps. Every
// frame is read, in file order, and each record out of order is named.
TEST_F(ForgedRecording, RecordsOutOfOrderAreReadAndNamed) {
  patchRecord(1, 8, uint64_t{0});       // frame 0 again
  patchRecord(2, 8, ~uint64_t{0} - 5);  // a wrapped index
  patchRecord(2, 24, int64_t{1});       // before frame 1's stamp
  std::ofstream(dir / "frames.ptv", std::ios::binary | std::ios::trunc) << bytes;
  auto r = Reader::open(dir);
  ASSERT_TRUE(r) << r.error().message;
  ASSERT_EQ(r->size(), 3U);
  ASSERT_EQ(r->warnings().size(), 3U);
  const std::string at1 = "frames.ptv: record at byte " + std::to_string(recordAt(1));
  const std::string at2 = "frames.ptv: record at byte " + std::to_string(recordAt(2));
  EXPECT_THAT(r->warnings()[0],
              ::testing::HasSubstr(at1 + " (frame 0): frame index does not follow"));
  EXPECT_THAT(r->warnings()[1], ::testing::HasSubstr(at2 + " (frame 18446744073709551610): "
                                                           "frame index above 2147483647"));
  EXPECT_THAT(r->warnings()[2], ::testing::HasSubstr("left timestamp 1 ns goes back"));
  cv::Mat l, rr;
  for (size_t i = 0; i < 3; ++i) EXPECT_TRUE(r->read(i, l, rr)) << i;
  reset();
  EXPECT_EQ(openError(), "opened with 3 frames");
}

TEST_F(Recording, ManifestRateMustBeARate) {
  record(2, 1);
  std::string text;
  {
    std::ifstream in(dir / "manifest.toml");
    text.assign(std::istreambuf_iterator<char>(in), {});
  }
  const size_t at = text.find("nominal_fps = ");
  ASSERT_NE(at, std::string::npos);
  const size_t end = text.find('\n', at);
  for (const char* v : {"nan", "inf", "-10", "0", "1e9", "\"fast\""}) {
    SCOPED_TRACE(v);
    std::string t = text;
    t.replace(at, end - at, std::string("nominal_fps = ") + v);
    std::ofstream(dir / "manifest.toml", std::ios::trunc) << t;
    auto r = Reader::open(dir);
    ASSERT_FALSE(r);
    EXPECT_THAT(r.error().message,
                ::testing::MatchesRegex(".*manifest.toml:[0-9]+: nominal_fps must be a number.*"));
  }
}

TEST_F(Recording, WriterRefusesToOverwriteAndBadFrames) {
  record(1, 1);
  auto again = Writer::create(dir, manifest(size), smallRig(size));
  ASSERT_FALSE(again);
  EXPECT_NE(again.error().message.find("never overwritten"), std::string::npos);
  auto w = Writer::create(tmp.path() / "other", manifest(size), smallRig(size));
  ASSERT_TRUE(w);
  auto bad = w->write({}, cv::Mat(10, 10, CV_8UC1), cv::Mat(10, 10, CV_8UC1));
  ASSERT_FALSE(bad);
  EXPECT_NE(bad.error().message.find("must be 160x120 gray8"), std::string::npos);
}

TEST(RecordingDiskFull, WriteFailsCleanlyAndTheRecordingStaysReadable) {
  // A child process whose file-size limit the kernel enforces (RLIMIT_FSIZE: write(2) fails
  // with EFBIG part-way through a record, as it would with ENOSPC on a full disk).
  test::TempDir tmp;
  const cv::Size size(64, 48);
  const auto dir = tmp.path() / "rec";
  const pid_t pid = ::fork();
  ASSERT_GE(pid, 0);
  if (pid == 0) {
    ::signal(SIGXFSZ, SIG_IGN);
    auto w = Writer::create(dir, manifest(size), smallRig(size), 0);  // raw: 6 KB per frame
    if (!w) ::_exit(10);
    rlimit lim{};
    lim.rlim_cur = lim.rlim_max = 50'000;
    if (::setrlimit(RLIMIT_FSIZE, &lim) != 0) ::_exit(11);
    for (uint64_t i = 0; i < 100; ++i) {
      auto ok = w->write({i, i, 0, 0, 0}, noiseImage(size, 1), noiseImage(size, 2));
      if (!ok) {
        const bool named = ok.error().message.find("frames.ptv: frame " + std::to_string(i) +
                                                   " not recorded") != std::string::npos;
        ::_exit(named && w->framesWritten() == i ? static_cast<int>(i) + 100 : 12);
      }
    }
    ::_exit(13);
  }
  int status = 0;
  ASSERT_EQ(::waitpid(pid, &status, 0), pid);
  ASSERT_TRUE(WIFEXITED(status));
  const int code = WEXITSTATUS(status);
  ASSERT_GE(code, 100) << "child exit " << code;
  const size_t written = static_cast<size_t>(code - 100);
  EXPECT_GT(written, 3U);
  auto r = Reader::open(dir);
  ASSERT_TRUE(r) << r.error().message;
  EXPECT_EQ(r->size(), written);
  EXPECT_EQ(r->truncation().value_or("none"), "none");  // truncated back to a clean end
  cv::Mat l, rr;
  EXPECT_TRUE(r->read(written - 1, l, rr));
}

}  // namespace
}  // namespace pulsetrack::record

namespace pulsetrack::record {
namespace {

TEST(TrackCsv, RoundTripKeepsEveryField) {
  test::TempDir tmp;
  const std::vector<TrackRow> rows = {
      {7, 0.7, 3, 101.25, 202.5, 99.125, 198.75, -1.5, 2.25, 451.125, 0.93, 0.61, "ok"},
      {8, 0.8, 4, 1, 2, 3, 4, 5, 6, 7, 0.1, 0.2, "occluded"}};
  ASSERT_TRUE(writeTrackCsv(tmp / "t.csv", rows));
  auto back = readTrackCsv(tmp / "t.csv");
  ASSERT_TRUE(back) << back.error().message;
  ASSERT_EQ(back->size(), 2U);
  const TrackRow& r = (*back)[0];
  EXPECT_EQ(r.frame, 7);
  EXPECT_DOUBLE_EQ(r.t, 0.7);
  EXPECT_EQ(r.id, 3);
  EXPECT_DOUBLE_EQ(r.xl, 101.25);
  EXPECT_DOUBLE_EQ(r.yl, 202.5);
  EXPECT_DOUBLE_EQ(r.xr, 99.125);
  EXPECT_DOUBLE_EQ(r.yr, 198.75);
  EXPECT_DOUBLE_EQ(r.x, -1.5);
  EXPECT_DOUBLE_EQ(r.y, 2.25);
  EXPECT_DOUBLE_EQ(r.z, 451.125);
  EXPECT_DOUBLE_EQ(r.ncc, 0.93);
  EXPECT_DOUBLE_EQ(r.nmi, 0.61);
  EXPECT_EQ(r.status, "ok");
  EXPECT_EQ((*back)[1].status, "occluded");
}

TEST(TrackCsv, BadFilesAreNamedWithTheLine) {
  test::TempDir tmp;
  std::ofstream(tmp / "h.csv") << "frame,t,id\n";
  auto r = readTrackCsv(tmp / "h.csv");
  ASSERT_FALSE(r);
  EXPECT_NE(r.error().message.find("h.csv:1: header must be"), std::string::npos)
      << r.error().message;
  std::ofstream(tmp / "s.csv") << kTrackCsvHeader << "\n1,0.1,2,3\n";
  r = readTrackCsv(tmp / "s.csv");
  ASSERT_FALSE(r);
  EXPECT_NE(r.error().message.find("s.csv:2: expected 13 fields, got 4"), std::string::npos)
      << r.error().message;
  std::ofstream(tmp / "n.csv") << kTrackCsvHeader << "\n1,abc,2,3,4,5,6,7,8,9,0.9,0.5,ok\n";
  r = readTrackCsv(tmp / "n.csv");
  ASSERT_FALSE(r);
  EXPECT_NE(r.error().message.find("n.csv:2: field 't' is not a number: 'abc'"), std::string::npos)
      << r.error().message;
}

// The live recorder: every offered pair on disk, in order, bit-exact.
TEST(LiveRecorder, RecordsTheLiveStreamLosslessly) {
  test::TempDir tmp;
  const cv::Size size(64, 48);
  LiveRecorderOptions o;
  o.dir = tmp.path() / "live";
  o.manifest = manifest(size);
  auto rec = LiveRecorder::start(o, smallRig(size));
  ASSERT_TRUE(rec) << rec.error().message;
  std::vector<std::pair<cv::Mat, cv::Mat>> sent;
  for (uint64_t i = 0; i < 50; ++i) {
    sent.emplace_back(noiseImage(size, static_cast<int>(2 * i)),
                      noiseImage(size, static_cast<int>(2 * i + 1)));
    ASSERT_TRUE((*rec)->offer(
        {i, 1000 + i, static_cast<int64_t>(i) * 100, static_cast<int64_t>(i) * 100 + 5, 0},
        sent.back().first, sent.back().second));
    std::this_thread::sleep_for(std::chrono::milliseconds(2));
  }
  (*rec)->stop();
  const RecorderStatus st = (*rec)->status();
  EXPECT_EQ(st.written, 50U);
  EXPECT_EQ(st.thinned, 0U);
  EXPECT_TRUE(st.error.empty());
  auto r = Reader::open(o.dir);
  ASSERT_TRUE(r) << r.error().message;
  ASSERT_EQ(r->size(), 50U);
  cv::Mat l, rr;
  for (size_t i = 0; i < 50; ++i) {
    ASSERT_TRUE(r->read(i, l, rr));
    EXPECT_EQ(cv::norm(l, sent[i].first, cv::NORM_INF), 0.0);
    EXPECT_EQ(cv::norm(rr, sent[i].second, cv::NORM_INF), 0.0);
    EXPECT_EQ(r->meta(i).trigger_seq, 1000 + i);
    EXPECT_EQ(r->meta(i).t_right_ns, static_cast<int64_t>(i) * 100 + 5);
  }
}

// A disk slower than the stream: capture never waits, the recording thins, what is written is
// in order and readable.
TEST(LiveRecorder, ASlowDiskThinsTheRecordingAndCaptureNeverWaits) {
  test::TempDir tmp;
  const cv::Size size(640, 480);
  LiveRecorderOptions o;
  o.dir = tmp.path() / "live";
  o.manifest = manifest(size);
  o.slots = 2;
  o.zstd_level = 19;  // slow on purpose
  auto rec = LiveRecorder::start(o, smallRig(size));
  ASSERT_TRUE(rec) << rec.error().message;
  const cv::Mat a = noiseImage(size, 1), b = noiseImage(size, 2);
  int taken = 0;
  const auto t0 = std::chrono::steady_clock::now();
  for (uint64_t i = 0; i < 200; ++i) taken += (*rec)->offer({i, i, 0, 0, 0}, a, b) ? 1 : 0;
  const double offer_s =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  (*rec)->stop();
  const RecorderStatus st = (*rec)->status();
  std::cout << "200 offers in " << offer_s * 1e3 << " ms: " << st.written << " written, "
            << st.thinned << " thinned\n";
  EXPECT_GT(st.thinned, 100U);
  EXPECT_EQ(st.written + st.thinned, 200U);
  EXPECT_EQ(static_cast<uint64_t>(taken), st.written);
  auto r = Reader::open(o.dir);
  ASSERT_TRUE(r);
  ASSERT_EQ(r->size(), st.written);
  for (size_t i = 1; i < r->size(); ++i) EXPECT_GT(r->meta(i).frame, r->meta(i - 1).frame);
}

// In a forked child (the caller's branch for pid 0): a recorder of 64x48 raw frames in `dir`
// under a 60 kB file-size limit (the kernel's, as a full disk fails a write: EFBIG); exits 10 or
// 11 when that cannot be set up.
std::unique_ptr<LiveRecorder> recorderUnderFileSizeLimit(const std::filesystem::path& dir,
                                                         int resume_check_ms) {
  ::signal(SIGXFSZ, SIG_IGN);
  const cv::Size size(64, 48);
  LiveRecorderOptions o;
  o.dir = dir;
  o.manifest = manifest(size);
  o.zstd_level = 0;
  o.resume_check_ms = resume_check_ms;
  auto rec = LiveRecorder::start(o, smallRig(size));
  if (!rec) ::_exit(10);
  rlimit lim{};
  lim.rlim_cur = lim.rlim_max = 60'000;
  if (::setrlimit(RLIMIT_FSIZE, &lim) != 0) ::_exit(11);
  return std::move(*rec);
}

// A disk that fills (the kernel's file-size limit in a child process): the recording stops
// cleanly with the error, offers are refused, the file reads back to its last frame.
TEST(LiveRecorder, AFullDiskStopsTheRecordingCleanly) {
  test::TempDir tmp;
  const cv::Size size(64, 48);
  const auto dir = tmp.path() / "live";
  const pid_t pid = ::fork();
  ASSERT_GE(pid, 0);
  if (pid == 0) {
    auto rec = recorderUnderFileSizeLimit(dir, 2000);  // no resume within the test
    for (uint64_t i = 0; i < 100; ++i) {
      (void)rec->offer({i, i, 0, 0, 0}, noiseImage(size, 1), noiseImage(size, 2));
      std::this_thread::sleep_for(std::chrono::milliseconds(3));
    }
    const RecorderStatus st = rec->status();
    const bool refused = !rec->offer({100, 100, 0, 0, 0}, noiseImage(size, 1), noiseImage(size, 2));
    rec->stop();
    if (!st.stopped || st.error.find("not recorded") == std::string::npos || !refused) ::_exit(12);
    ::_exit(static_cast<int>(std::min<uint64_t>(st.written, 90)) + 1);
  }
  int status = 0;
  ASSERT_EQ(::waitpid(pid, &status, 0), pid);
  ASSERT_TRUE(WIFEXITED(status));
  const int code = WEXITSTATUS(status);
  ASSERT_GT(code, 1) << "child failed with " << code;
  ASSERT_LT(code, 10 + 1) << "child failed with " << code;  // ~6 KB per frame: 8 or 9 fit
  auto r = Reader::open(dir);
  ASSERT_TRUE(r) << r.error().message;
  EXPECT_EQ(r->size(), static_cast<size_t>(code - 1));
  cv::Mat l, rr;
  for (size_t i = 0; i < r->size(); ++i) EXPECT_TRUE(r->read(i, l, rr));
}

// The disk below the reserve (the free-space seam: a test cannot fill a real disk): the segment
// stops cleanly, offers while stopped are counted, and once the reserve and a margin are free
// the recorder resumes by itself in DIR-part2, a complete recording whose frames start at 0.
TEST(LiveRecorder, BelowTheReserveItStopsAndResumesInANewSegmentWhenThereIsRoom) {
  test::TempDir tmp;
  const cv::Size size(64, 48);
  std::atomic<uint64_t> free_bytes{uint64_t{10} << 30};
  LiveRecorderOptions o;
  o.dir = tmp.path() / "live";
  o.manifest = manifest(size);
  o.min_free_bytes = uint64_t{1} << 30;
  o.resume_check_ms = 20;
  o.free_bytes = [&](const std::filesystem::path&) { return free_bytes.load(); };
  auto rec = LiveRecorder::start(o, smallRig(size));
  ASSERT_TRUE(rec) << rec.error().message;
  const auto offer = [&](uint64_t i) {
    return (*rec)->offer({i, 500 + i, static_cast<int64_t>(i), static_cast<int64_t>(i), 0},
                         noiseImage(size, static_cast<int>(i)), noiseImage(size, 1000));
  };
  const auto waitFor = [&](auto pred) {
    for (int k = 0; k < 1000 && !pred((*rec)->status()); ++k)
      std::this_thread::sleep_for(std::chrono::milliseconds(10));
    return pred((*rec)->status());
  };
  for (uint64_t i = 0; i < 10; ++i) ASSERT_TRUE(offer(i));
  ASSERT_TRUE(waitFor([](const RecorderStatus& s) { return s.written == 10; }));
  free_bytes = uint64_t{900} << 20;  // below the reserve
  ASSERT_TRUE(offer(10));            // taken; the writer finds the disk too full for it
  ASSERT_TRUE(waitFor([](const RecorderStatus& s) { return s.stopped; }));
  RecorderStatus st = (*rec)->status();
  EXPECT_EQ(st.faults, 1U);
  EXPECT_EQ(st.written, 10U);
  EXPECT_NE(st.error.find("the disk is almost full: 943 MB free, below the 1073 MB reserve"),
            std::string::npos)
      << st.error;
  EXPECT_NE(st.error.find((tmp.path() / "live").string()), std::string::npos) << st.error;
  for (uint64_t i = 11; i < 16; ++i) EXPECT_FALSE(offer(i));
  EXPECT_EQ((*rec)->status().unrecorded, 5U);
  // Room again, but not the reserve and its margin: still stopped.
  free_bytes = (uint64_t{1} << 30) + (uint64_t{100} << 20);
  std::this_thread::sleep_for(std::chrono::milliseconds(100));
  EXPECT_TRUE((*rec)->status().stopped);
  free_bytes = uint64_t{2} << 30;
  ASSERT_TRUE(waitFor([](const RecorderStatus& s) { return !s.stopped; }));
  for (uint64_t i = 20; i < 27; ++i) ASSERT_TRUE(offer(i));
  (*rec)->stop();
  st = (*rec)->status();
  EXPECT_EQ(st.segment, 2);
  EXPECT_EQ(st.dir, tmp.path() / "live-part2");
  EXPECT_EQ(st.written, 17U);
  EXPECT_TRUE(st.error.empty()) << st.error;
  auto first = Reader::open(tmp.path() / "live");
  ASSERT_TRUE(first) << first.error().message;
  EXPECT_EQ(first->size(), 10U);
  EXPECT_FALSE(first->truncation().has_value());
  auto second = Reader::open(tmp.path() / "live-part2");
  ASSERT_TRUE(second) << second.error().message;
  ASSERT_EQ(second->size(), 7U);
  cv::Mat l, r;
  for (size_t i = 0; i < 7; ++i) {
    EXPECT_EQ(second->meta(i).frame, i);  // the segment's own numbering
    EXPECT_EQ(second->meta(i).trigger_seq, 520 + i);
    ASSERT_TRUE(second->read(i, l, r));
    EXPECT_EQ(cv::norm(l, noiseImage(size, static_cast<int>(20 + i)), cv::NORM_INF), 0.0);
  }
}

// A write that fails (the kernel's file-size limit) also resumes, in a new segment, when the
// file system has room: the new file starts empty.
TEST(LiveRecorder, AFailedWriteResumesInANewSegment) {
  test::TempDir tmp;
  const cv::Size size(64, 48);
  const auto dir = tmp.path() / "live";
  const pid_t pid = ::fork();
  ASSERT_GE(pid, 0);
  if (pid == 0) {
    auto rec = recorderUnderFileSizeLimit(dir, 20);
    int segment = 1;
    for (uint64_t i = 0; i < 400 && segment < 3; ++i) {
      (void)rec->offer({i, i, 0, 0, 0}, noiseImage(size, 1), noiseImage(size, 2));
      std::this_thread::sleep_for(std::chrono::milliseconds(3));
      segment = rec->status().segment;
    }
    rec->stop();
    const RecorderStatus st = rec->status();
    ::_exit(st.segment >= 3 && st.faults >= 2 ? 0 : 12);
  }
  int status = 0;
  ASSERT_EQ(::waitpid(pid, &status, 0), pid);
  ASSERT_TRUE(WIFEXITED(status));
  ASSERT_EQ(WEXITSTATUS(status), 0);
  for (const char* part : {"live", "live-part2"}) {
    auto r = Reader::open(tmp.path() / part);
    ASSERT_TRUE(r) << part << ": " << r.error().message;
    EXPECT_GE(r->size(), 5U) << part;
    EXPECT_EQ(r->meta(0).frame, 0U) << part;
  }
}

}  // namespace
}  // namespace pulsetrack::record
