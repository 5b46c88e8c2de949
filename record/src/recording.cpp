#include "pulsetrack/record/recording.hpp"

#include <fcntl.h>
#include <fmt/format.h>
#include <sys/stat.h>
#include <toml++/toml.h>
#include <unistd.h>
#include <zlib.h>
#include <zstd.h>

#include <bit>
#include <cerrno>
#include <cmath>
#include <cstring>
#include <ctime>
#include <fstream>
#include <iterator>

#include "pulsetrack/cfg/table_reader.hpp"

namespace pulsetrack::record {

static_assert(std::endian::native == std::endian::little,
              "the recording format is little-endian; a big-endian port must swap fields");

using vision::fail;

namespace {

constexpr char kFileMagic[8] = {'P', 'T', 'R', 'K', 'S', 'T', 'R', '1'};
constexpr uint32_t kRecordMagic = 0x52465450;  // "PTFR"
constexpr uint32_t kPixelGray8 = 1;
constexpr uint32_t kCodecRaw = 0;
constexpr uint32_t kCodecZstd = 1;
// No recording reaches it (248 days at 100 Hz); a larger index is a corrupt or forged record.
constexpr uint64_t kMaxFrameIndex = (1ULL << 31) - 1;
constexpr size_t kMaxWarnings = 8;  // listed; more are summed up in one line

struct FileHeader {
  char magic[8];
  uint32_t version;
  uint32_t header_size;
  uint32_t width;
  uint32_t height;
  uint32_t pixel_format;
  uint32_t header_crc;  // CRC-32 of the bytes before it
};
static_assert(sizeof(FileHeader) == 32);

struct RecordHeader {
  uint32_t magic;
  uint32_t header_size;
  uint64_t frame;
  uint64_t trigger_seq;
  int64_t t_left_ns;
  int64_t t_right_ns;
  uint32_t flags;
  uint32_t codec;
  uint32_t left_bytes;
  uint32_t right_bytes;
  uint32_t payload_crc;  // CRC-32 of left then right payload
  uint32_t header_crc;   // CRC-32 of the bytes before it
};
static_assert(sizeof(RecordHeader) == 64);

template <class T>
uint32_t crcOfPrefix(const T& h) {
  return static_cast<uint32_t>(crc32(0L, reinterpret_cast<const Bytef*>(&h),
                                     static_cast<uInt>(sizeof(T) - sizeof(uint32_t))));
}

uint32_t crcUpdate(uint32_t crc, const void* data, size_t n) {
  return static_cast<uint32_t>(crc32(crc, static_cast<const Bytef*>(data), static_cast<uInt>(n)));
}

std::string errnoText(int e) { return std::strerror(e); }

// write(2) until done; returns 0 or errno.
int writeAll(int fd, const void* data, size_t n) {
  const auto* p = static_cast<const uint8_t*>(data);
  while (n > 0) {
    const ssize_t w = ::write(fd, p, n);
    if (w < 0) {
      if (errno == EINTR) continue;
      return errno;
    }
    p += w;
    n -= static_cast<size_t>(w);
  }
  return 0;
}

std::string nowIso8601() {
  const std::time_t t = std::time(nullptr);
  std::tm tm{};
  gmtime_r(&t, &tm);
  char buf[32];
  std::strftime(buf, sizeof buf, "%Y-%m-%dT%H:%M:%SZ", &tm);
  return buf;
}

std::string tomlString(const std::string& s) {
  std::string out = "\"";
  for (char c : s) {
    if (c == '"' || c == '\\') out += '\\';
    out += c;
  }
  return out + "\"";
}

}  // namespace

// ---------------------------------------------------------------------------------------------
struct Writer::Impl {
  std::filesystem::path dir;
  std::filesystem::path frames_path;
  Manifest manifest;
  int fd = -1;
  int csv_fd = -1;
  int level = 1;
  ZSTD_CCtx* cctx = nullptr;
  std::vector<uint8_t> buffer;  // header + left + right, sized once
  uint64_t frames = 0;
  uint64_t bytes = 0;
  off_t good_end = 0;  // the file ends here after the last complete record

  ~Impl() {
    if (fd >= 0) ::close(fd);
    if (csv_fd >= 0) ::close(csv_fd);
    if (cctx != nullptr) ZSTD_freeCCtx(cctx);
  }
};

Writer::Writer(std::unique_ptr<Impl> impl) : impl_(std::move(impl)) {}
Writer::Writer(Writer&&) noexcept = default;
Writer& Writer::operator=(Writer&&) noexcept = default;
Writer::~Writer() {
  if (impl_) (void)close();
}

Result<Writer> Writer::create(const std::filesystem::path& dir, const Manifest& manifest_in,
                              const vision::StereoRig& rig, int zstd_level) {
  auto impl = std::make_unique<Impl>();
  impl->dir = dir;
  impl->manifest = manifest_in;
  impl->manifest.version = kFormatVersion;
  if (impl->manifest.created.empty()) impl->manifest.created = nowIso8601();
  const Manifest& m = impl->manifest;
  if (m.width <= 0 || m.height <= 0) {
    return fail(fmt::format("{}: recording needs a positive image size, got {}x{}", dir.string(),
                            m.width, m.height));
  }
  if (m.pixel_format != "gray8") {
    return fail(fmt::format("{}: pixel format '{}' is not supported (gray8)", dir.string(),
                            m.pixel_format));
  }
  std::error_code ec;
  if (std::filesystem::exists(dir, ec) && !std::filesystem::is_empty(dir, ec)) {
    return fail(fmt::format("{}: already exists and is not empty; a recording is never overwritten",
                            dir.string()));
  }
  std::filesystem::create_directories(dir, ec);
  if (ec) return fail(fmt::format("{}: cannot create: {}", dir.string(), ec.message()));

  if (auto ok = vision::saveRig(rig, dir / "rig.yaml"); !ok) return std::unexpected(ok.error());
  {
    const std::string text = fmt::format(
        "# pulsetrack recording (docs/recording-format.md)\n"
        "format = \"pulsetrack-recording\"\n"
        "version = {}\n"
        "source = {}\n"
        "rig_id = {}\n"
        "width = {}\n"
        "height = {}\n"
        "pixel_format = {}\n"
        "{}"
        "created = {}\n",
        m.version, tomlString(m.source), tomlString(m.rig_id), m.width, m.height,
        tomlString(m.pixel_format),
        // Unknown (0) is left out: the reader takes a present nominal_fps to be a rate.
        m.nominal_fps > 0.0 ? fmt::format("nominal_fps = {}\n", m.nominal_fps) : std::string(),
        tomlString(m.created));
    const auto path = dir / "manifest.toml";
    const int mfd = ::open(path.c_str(), O_WRONLY | O_CREAT | O_TRUNC | O_CLOEXEC, 0644);
    if (mfd < 0) return fail(fmt::format("{}: cannot create: {}", path.string(), errnoText(errno)));
    const int err = writeAll(mfd, text.data(), text.size());
    ::close(mfd);
    if (err != 0) return fail(fmt::format("{}: write failed: {}", path.string(), errnoText(err)));
  }

  impl->frames_path = dir / "frames.ptv";
  impl->fd = ::open(impl->frames_path.c_str(), O_WRONLY | O_CREAT | O_TRUNC | O_CLOEXEC, 0644);
  if (impl->fd < 0) {
    return fail(fmt::format("{}: cannot create: {}", impl->frames_path.string(), errnoText(errno)));
  }
  FileHeader fh{};
  std::memcpy(fh.magic, kFileMagic, sizeof fh.magic);
  fh.version = kFormatVersion;
  fh.header_size = sizeof(FileHeader);
  fh.width = static_cast<uint32_t>(m.width);
  fh.height = static_cast<uint32_t>(m.height);
  fh.pixel_format = kPixelGray8;
  fh.header_crc = crcOfPrefix(fh);
  if (int err = writeAll(impl->fd, &fh, sizeof fh); err != 0) {
    return fail(fmt::format("{}: write failed: {}", impl->frames_path.string(), errnoText(err)));
  }
  impl->good_end = sizeof fh;

  const auto csv = dir / "frames.csv";
  impl->csv_fd = ::open(csv.c_str(), O_WRONLY | O_CREAT | O_TRUNC | O_CLOEXEC, 0644);
  if (impl->csv_fd < 0)
    return fail(fmt::format("{}: cannot create: {}", csv.string(), errnoText(errno)));
  const std::string head = "frame,trigger_seq,t_left_ns,t_right_ns,flags\n";
  if (int err = writeAll(impl->csv_fd, head.data(), head.size()); err != 0) {
    return fail(fmt::format("{}: write failed: {}", csv.string(), errnoText(err)));
  }

  impl->level = zstd_level;
  const size_t image = static_cast<size_t>(m.width) * static_cast<size_t>(m.height);
  const size_t bound = zstd_level > 0 ? ZSTD_compressBound(image) : image;
  impl->buffer.resize(sizeof(RecordHeader) + 2 * bound);
  if (zstd_level > 0) {
    impl->cctx = ZSTD_createCCtx();
    if (impl->cctx == nullptr) return fail("zstd: cannot create a compression context");
  }
  return Writer(std::move(impl));
}

Result<void> Writer::write(const FrameMeta& meta, const cv::Mat& left, const cv::Mat& right) {
  Impl& w = *impl_;
  if (w.fd < 0) return fail(fmt::format("{}: recording is closed", w.frames_path.string()));
  const cv::Size size(w.manifest.width, w.manifest.height);
  for (const cv::Mat* img : {&left, &right}) {
    if (img->type() != CV_8UC1 || img->size() != size) {
      return fail(fmt::format("{}: frame {} must be {}x{} gray8, got {}x{} type {}",
                              w.frames_path.string(), meta.frame, size.width, size.height,
                              img->cols, img->rows, img->type()));
    }
  }
  const size_t image = static_cast<size_t>(size.area());
  auto* header = reinterpret_cast<RecordHeader*>(w.buffer.data());
  uint8_t* payload = w.buffer.data() + sizeof(RecordHeader);
  size_t sizes[2] = {0, 0};
  size_t used = 0;
  const cv::Mat* images[2] = {&left, &right};
  for (int k = 0; k < 2; ++k) {
    const cv::Mat src = images[k]->isContinuous() ? *images[k] : images[k]->clone();
    if (w.level > 0) {
      const size_t n =
          ZSTD_compressCCtx(w.cctx, payload + used, w.buffer.size() - sizeof(RecordHeader) - used,
                            src.data, image, w.level);
      if (ZSTD_isError(n) != 0U) {
        return fail(fmt::format("{}: zstd: {}", w.frames_path.string(), ZSTD_getErrorName(n)));
      }
      sizes[k] = n;
    } else {
      std::memcpy(payload + used, src.data, image);
      sizes[k] = image;
    }
    used += sizes[k];
  }
  RecordHeader h{};
  h.magic = kRecordMagic;
  h.header_size = sizeof(RecordHeader);
  h.frame = meta.frame;
  h.trigger_seq = meta.trigger_seq;
  h.t_left_ns = meta.t_left_ns;
  h.t_right_ns = meta.t_right_ns;
  h.flags = meta.flags;
  h.codec = w.level > 0 ? kCodecZstd : kCodecRaw;
  h.left_bytes = static_cast<uint32_t>(sizes[0]);
  h.right_bytes = static_cast<uint32_t>(sizes[1]);
  h.payload_crc = crcUpdate(0, payload, used);
  h.header_crc = crcOfPrefix(h);
  *header = h;
  const size_t total = sizeof(RecordHeader) + used;
  if (int err = writeAll(w.fd, w.buffer.data(), total); err != 0) {
    // Leave the file ending in the last complete record (disk full, I/O error).
    if (::ftruncate(w.fd, w.good_end) == 0) (void)::lseek(w.fd, w.good_end, SEEK_SET);
    return fail(fmt::format("{}: frame {} not recorded: {}", w.frames_path.string(), meta.frame,
                            errnoText(err)));
  }
  w.good_end += static_cast<off_t>(total);
  ++w.frames;
  w.bytes += total;
  char line[128];
  const int n = std::snprintf(
      line, sizeof line, "%llu,%llu,%lld,%lld,%u\n", static_cast<unsigned long long>(meta.frame),
      static_cast<unsigned long long>(meta.trigger_seq), static_cast<long long>(meta.t_left_ns),
      static_cast<long long>(meta.t_right_ns), meta.flags);
  if (int err = writeAll(w.csv_fd, line, static_cast<size_t>(n)); err != 0) {
    return fail(fmt::format("{}: frames.csv: {}", w.dir.string(), errnoText(err)));
  }
  return {};
}

Result<void> Writer::sync() {
  Impl& w = *impl_;
  if (w.fd >= 0 && ::fdatasync(w.fd) != 0) {
    return fail(fmt::format("{}: fdatasync: {}", w.frames_path.string(), errnoText(errno)));
  }
  if (w.csv_fd >= 0) (void)::fdatasync(w.csv_fd);
  return {};
}

Result<void> Writer::close() {
  if (!impl_ || impl_->fd < 0) return {};
  auto synced = sync();
  ::close(impl_->fd);
  impl_->fd = -1;
  if (impl_->csv_fd >= 0) ::close(impl_->csv_fd);
  impl_->csv_fd = -1;
  return synced;
}

uint64_t Writer::framesWritten() const { return impl_->frames; }
uint64_t Writer::bytesWritten() const { return impl_->bytes; }
const std::filesystem::path& Writer::dir() const { return impl_->dir; }

// ---------------------------------------------------------------------------------------------
struct Reader::Impl {
  struct Entry {
    FrameMeta meta;
    off_t offset = 0;  // of the payload
    uint32_t codec = 0;
    uint32_t left_bytes = 0;
    uint32_t right_bytes = 0;
    uint32_t payload_crc = 0;
  };
  std::filesystem::path dir;
  std::filesystem::path frames_path;
  Manifest manifest;
  vision::StereoRig rig;
  std::vector<Entry> index;
  std::optional<std::string> truncation;
  std::vector<std::string> warnings;
  int fd = -1;
  ZSTD_DCtx* dctx = nullptr;
  std::vector<uint8_t> payload;

  ~Impl() {
    if (fd >= 0) ::close(fd);
    if (dctx != nullptr) ZSTD_freeDCtx(dctx);
  }
  Result<void> readPayload(const Entry& e) {
    const size_t n = static_cast<size_t>(e.left_bytes) + e.right_bytes;
    payload.resize(n);
    size_t done = 0;
    while (done < n) {
      const ssize_t r =
          ::pread(fd, payload.data() + done, n - done, e.offset + static_cast<off_t>(done));
      if (r < 0 && errno == EINTR) continue;
      if (r <= 0) {
        return fail(fmt::format("{}: frame {}: read failed: {}", frames_path.string(), e.meta.frame,
                                r < 0 ? errnoText(errno) : "unexpected end of file"));
      }
      done += static_cast<size_t>(r);
    }
    if (crcUpdate(0, payload.data(), n) != e.payload_crc) {
      return fail(fmt::format("{}: frame {}: payload CRC mismatch (corrupt data at byte {})",
                              frames_path.string(), e.meta.frame,
                              static_cast<long long>(e.offset)));
    }
    return {};
  }
};

Reader::Reader(std::unique_ptr<Impl> impl) : impl_(std::move(impl)) {}
Reader::Reader(Reader&&) noexcept = default;
Reader& Reader::operator=(Reader&&) noexcept = default;
Reader::~Reader() = default;

namespace {

Result<Manifest> readManifest(const std::filesystem::path& path) {
  // Read and parsed as every TOML file of the project is (cfg: bounded size, non-ASCII outside
  // strings refused before toml++ sees it).
  std::string text;
  if (std::string error; !cfg::readTomlText(path, "manifest", text, error)) return fail(error);
  toml::table t;
  if (std::string error; !cfg::parseToml(text, path.string(), t, error)) return fail(error);
  Manifest m;
  const auto need = [&](const char* key) -> Result<const toml::node*> {
    const toml::node* n = t.get(key);
    if (n == nullptr) return fail(fmt::format("{}: key '{}' is missing", path.string(), key));
    return n;
  };
  const auto line = [&](const toml::node* n) { return n->source().begin.line; };
  auto fmt_node = need("format");
  if (!fmt_node) return std::unexpected(fmt_node.error());
  if ((*fmt_node)->value<std::string>() != "pulsetrack-recording") {
    return fail(fmt::format("{}:{}: format must be \"pulsetrack-recording\"", path.string(),
                            line(*fmt_node)));
  }
  auto version = need("version");
  if (!version) return std::unexpected(version.error());
  const auto v = (*version)->value<int64_t>();
  if (!v)
    return fail(fmt::format("{}:{}: version must be an integer", path.string(), line(*version)));
  if (*v > kFormatVersion || *v < 1) {
    return fail(
        fmt::format("{}:{}: recording format version {} is not one this pulsetrack reads "
                    "(1 to {})",
                    path.string(), line(*version), *v, kFormatVersion));
  }
  m.version = static_cast<int>(*v);
  for (const char* key : {"width", "height"}) {
    auto n = need(key);
    if (!n) return std::unexpected(n.error());
    const auto x = (*n)->value<int64_t>();
    if (!x || *x <= 0 || *x > 65535) {
      return fail(
          fmt::format("{}:{}: {} must be an integer in 1..65535", path.string(), line(*n), key));
    }
    (std::string(key) == "width" ? m.width : m.height) = static_cast<int>(*x);
  }
  m.source = t["source"].value_or(std::string());
  m.rig_id = t["rig_id"].value_or(std::string());
  m.pixel_format = t["pixel_format"].value_or(std::string("gray8"));
  if (const toml::node* fps = t.get("nominal_fps")) {
    const auto rate = fps->value<double>();
    if (!rate || !std::isfinite(*rate) || *rate <= 0.0 || *rate > 10000.0) {
      return fail(fmt::format("{}:{}: nominal_fps must be a number above 0 and up to 10000",
                              path.string(), line(fps)));
    }
    m.nominal_fps = *rate;
  }
  m.created = t["created"].value_or(std::string());
  if (m.pixel_format != "gray8") {
    return fail(fmt::format("{}: pixel_format '{}' is not supported (gray8)", path.string(),
                            m.pixel_format));
  }
  return m;
}

}  // namespace

Result<Reader> Reader::open(const std::filesystem::path& dir) {
  auto impl = std::make_unique<Impl>();
  impl->dir = dir;
  std::error_code ec;
  if (!std::filesystem::is_directory(dir, ec)) {
    return fail(fmt::format("{}: not a recording folder (does not exist or is not a folder)",
                            dir.string()));
  }
  auto manifest = readManifest(dir / "manifest.toml");
  if (!manifest) return std::unexpected(manifest.error());
  impl->manifest = *manifest;
  auto rig = vision::loadRig(dir / "rig.yaml");
  if (!rig) return std::unexpected(rig.error());
  impl->rig = *rig;

  impl->frames_path = dir / "frames.ptv";
  const std::string fp = impl->frames_path.string();
  impl->fd = ::open(impl->frames_path.c_str(), O_RDONLY | O_CLOEXEC);
  if (impl->fd < 0) return fail(fmt::format("{}: cannot open: {}", fp, errnoText(errno)));
  struct stat st {};
  if (::fstat(impl->fd, &st) != 0) return fail(fmt::format("{}: stat: {}", fp, errnoText(errno)));
  const off_t file_size = st.st_size;
  FileHeader fh{};
  if (::pread(impl->fd, &fh, sizeof fh, 0) != static_cast<ssize_t>(sizeof fh)) {
    return fail(fmt::format("{}: too short for a frames file header", fp));
  }
  if (std::memcmp(fh.magic, kFileMagic, sizeof fh.magic) != 0) {
    return fail(fmt::format("{}: not a pulsetrack frames file (bad magic)", fp));
  }
  if (fh.header_crc != crcOfPrefix(fh))
    return fail(fmt::format("{}: file header CRC mismatch", fp));
  if (fh.version < 1 || fh.version > static_cast<uint32_t>(kFormatVersion)) {
    return fail(
        fmt::format("{}: frames file version {} is not one this pulsetrack reads", fp, fh.version));
  }
  if (fh.header_size != sizeof fh) {
    return fail(fmt::format("{}: file header size {} (version {} has {})", fp, fh.header_size,
                            fh.version, sizeof fh));
  }
  if (fh.pixel_format != kPixelGray8) {
    return fail(fmt::format("{}: pixel format {} is not one this pulsetrack reads (1: 8-bit grey)",
                            fp, fh.pixel_format));
  }
  if (static_cast<int>(fh.width) != impl->manifest.width ||
      static_cast<int>(fh.height) != impl->manifest.height) {
    return fail(fmt::format("{}: frames are {}x{} but manifest.toml says {}x{}", fp, fh.width,
                            fh.height, impl->manifest.width, impl->manifest.height));
  }
  const cv::Size rig_size = impl->rig.left.imageSize();
  if (rig_size.width != impl->manifest.width || rig_size.height != impl->manifest.height) {
    return fail(fmt::format("{}: rig.yaml is calibrated for {}x{} but the frames are {}x{}",
                            dir.string(), rig_size.width, rig_size.height, impl->manifest.width,
                            impl->manifest.height));
  }
  const uint64_t image_bytes = static_cast<uint64_t>(fh.width) * fh.height;
  const uint64_t max_payload =
      2ULL * (ZSTD_compressBound(static_cast<size_t>(fh.width) * fh.height));

  off_t offset = fh.header_size;
  while (offset < file_size) {
    RecordHeader h{};
    const ssize_t got = ::pread(impl->fd, &h, sizeof h, offset);
    if (got != static_cast<ssize_t>(sizeof h)) {
      impl->truncation =
          fmt::format("incomplete record header at byte {} (file cut after {} frames)",
                      static_cast<long long>(offset), impl->index.size());
      break;
    }
    if (h.magic != kRecordMagic || h.header_crc != crcOfPrefix(h) || h.header_size != sizeof h ||
        static_cast<uint64_t>(h.left_bytes) + h.right_bytes > max_payload) {
      impl->truncation = fmt::format("bad record header at byte {} after {} frames",
                                     static_cast<long long>(offset), impl->index.size());
      break;
    }
    const off_t end = offset + static_cast<off_t>(sizeof h) + h.left_bytes + h.right_bytes;
    if (end > file_size) {
      impl->truncation = fmt::format("frame {} at byte {} is incomplete (file cut after {} frames)",
                                     h.frame, static_cast<long long>(offset), impl->index.size());
      break;
    }
    // A record whose header is intact (its CRC holds) but whose fields no writer produces is
    // an error, not a truncation: the file was made or changed by something else.
    const auto bad = [&](const std::string& what) {
      return fail(fmt::format("{}: record at byte {} (frame {}): {}", fp,
                              static_cast<long long>(offset), h.frame, what));
    };
    // Order is a warning, not an error: a daemon recording across a camera reopen restarts its
    // trigger numbering, and a looped replay recorded again repeats its stamps. The frames are
    // read in file order either way; a tool says so (warnings()) instead of refusing the whole
    // recording.
    const auto warn = [&](const std::string& what) {
      if (impl->warnings.size() < kMaxWarnings) {
        impl->warnings.push_back(fmt::format("{}: record at byte {} (frame {}): {}", fp,
                                             static_cast<long long>(offset), h.frame, what));
      } else if (impl->warnings.size() == kMaxWarnings) {
        impl->warnings.emplace_back("(more records out of order: not listed)");
      }
    };
    if (h.frame > kMaxFrameIndex) {
      warn(fmt::format("frame index above {} (248 days at 100 Hz)", kMaxFrameIndex));
    } else if (!impl->index.empty() && h.frame <= impl->index.back().meta.frame) {
      warn(fmt::format("frame index does not follow the previous record's frame {}",
                       impl->index.back().meta.frame));
    }
    if (h.t_left_ns < 0 || h.t_right_ns < 0) {
      return bad(
          fmt::format("negative timestamp (left {} ns, right {} ns)", h.t_left_ns, h.t_right_ns));
    }
    if (!impl->index.empty() && h.t_left_ns < impl->index.back().meta.t_left_ns) {
      warn(fmt::format("left timestamp {} ns goes back from the previous frame's {} ns",
                       h.t_left_ns, impl->index.back().meta.t_left_ns));
    }
    if (h.flags != 0) return bad(fmt::format("flags {:#x} are reserved (0 in version 1)", h.flags));
    if (h.codec != kCodecRaw && h.codec != kCodecZstd)
      return bad(fmt::format("codec {} is not one this pulsetrack reads (0 raw, 1 zstd)", h.codec));
    if (h.codec == kCodecRaw && (h.left_bytes != image_bytes || h.right_bytes != image_bytes)) {
      return bad(fmt::format("raw images of {} and {} bytes, the frames are {}x{} ({} bytes)",
                             h.left_bytes, h.right_bytes, fh.width, fh.height, image_bytes));
    }
    Impl::Entry e;
    e.meta = {h.frame, h.trigger_seq, h.t_left_ns, h.t_right_ns, h.flags};
    e.offset = offset + static_cast<off_t>(sizeof h);
    e.codec = h.codec;
    e.left_bytes = h.left_bytes;
    e.right_bytes = h.right_bytes;
    e.payload_crc = h.payload_crc;
    impl->index.push_back(e);
    offset = end;
  }
  // A power cut can leave the last record's length on disk but not its data: check it.
  if (!impl->index.empty()) {
    if (auto ok = impl->readPayload(impl->index.back()); !ok) {
      impl->truncation = fmt::format("last frame {} failed its CRC and was dropped",
                                     impl->index.back().meta.frame);
      impl->index.pop_back();
    }
  }
  impl->dctx = ZSTD_createDCtx();
  if (impl->dctx == nullptr) return fail("zstd: cannot create a decompression context");
  return Reader(std::move(impl));
}

const Manifest& Reader::manifest() const { return impl_->manifest; }
const vision::StereoRig& Reader::rig() const { return impl_->rig; }
size_t Reader::size() const { return impl_->index.size(); }
const FrameMeta& Reader::meta(size_t index) const { return impl_->index.at(index).meta; }
const std::optional<std::string>& Reader::truncation() const { return impl_->truncation; }
const std::vector<std::string>& Reader::warnings() const { return impl_->warnings; }
const std::filesystem::path& Reader::dir() const { return impl_->dir; }

Result<void> Reader::read(size_t index, cv::Mat& left, cv::Mat& right) {
  Impl& r = *impl_;
  if (index >= r.index.size()) {
    return fail(fmt::format("{}: frame index {} out of range (recording has {})",
                            r.frames_path.string(), index, r.index.size()));
  }
  const Impl::Entry& e = r.index[index];
  if (auto ok = r.readPayload(e); !ok) return ok;
  const cv::Size size(r.manifest.width, r.manifest.height);
  const size_t image = static_cast<size_t>(size.area());
  left.create(size, CV_8UC1);
  right.create(size, CV_8UC1);
  const uint8_t* src = r.payload.data();
  cv::Mat* dst[2] = {&left, &right};
  const uint32_t n[2] = {e.left_bytes, e.right_bytes};
  for (int k = 0; k < 2; ++k) {
    if (e.codec == kCodecZstd) {
      const size_t got = ZSTD_decompressDCtx(r.dctx, dst[k]->data, image, src, n[k]);
      if (ZSTD_isError(got) != 0U || got != image) {
        return fail(fmt::format("{}: frame {}: {} image does not decode ({})",
                                r.frames_path.string(), e.meta.frame, k == 0 ? "left" : "right",
                                ZSTD_isError(got) != 0U ? ZSTD_getErrorName(got) : "wrong size"));
      }
    } else if (e.codec == kCodecRaw && n[k] == image) {
      std::memcpy(dst[k]->data, src, image);
    } else {
      return fail(fmt::format("{}: frame {}: unknown codec {} or wrong size",
                              r.frames_path.string(), e.meta.frame, e.codec));
    }
    src += n[k];
  }
  return {};
}

}  // namespace pulsetrack::record
