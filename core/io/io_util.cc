#include "core/io/io_util.h"

#include <zlib.h>

#include <algorithm>
#include <cctype>
#include <cerrno>
#include <cstring>
#include <system_error>

#include "core/common/status.h"

namespace decima::io::internal {
namespace {

namespace fs = std::filesystem;

// The deflate format cannot compress better than about 1032:1 (zlib FAQ: a 258-byte match
// costs at least two bits), so C compressed bytes can never inflate to more than 1032 * C.
constexpr int64_t kMaxInflateRatio = 1032;
// Compressed input is inflated into a buffer grown in steps of this many bytes (doubling after).
constexpr size_t kGrowStep = size_t{16} << 20;
constexpr size_t kInputChunk = size_t{256} << 10;

}  // namespace

absl::StatusOr<int64_t> RegularFileSize(const fs::path& path) {
  std::error_code ec;
  const fs::file_status st = fs::status(path, ec);
  if (ec || !fs::exists(st)) {
    return absl::NotFoundError(absl::StrCat(path.string(), ": file does not exist"));
  }
  if (fs::is_directory(st)) {
    return Invalid(path, "is a directory, expected a file");
  }
  if (!fs::is_regular_file(st)) return Invalid(path, "is not a regular file");
  const auto size = fs::file_size(path, ec);
  if (ec) return Invalid(path, "cannot read file size: ", ec.message());
  return static_cast<int64_t>(size);
}

absl::StatusOr<std::string> ReadFileHead(const fs::path& path, size_t max_bytes) {
  DECIMA_ASSIGN_OR_RETURN(const int64_t size, RegularFileSize(path));
  std::FILE* f = std::fopen(path.c_str(), "rb");
  if (f == nullptr) {
    return absl::ErrnoToStatus(errno, absl::StrCat(path.string(), ": cannot open"));
  }
  std::string head(std::min<size_t>(max_bytes, static_cast<size_t>(size)), '\0');
  const size_t got = std::fread(head.data(), 1, head.size(), f);
  std::fclose(f);
  head.resize(got);
  return head;
}

bool HasGzipMagic(absl::string_view head) {
  return head.size() >= 2 && static_cast<uint8_t>(head[0]) == 0x1f &&
         static_cast<uint8_t>(head[1]) == 0x8b;
}

struct InputStream::State {
  fs::path path;
  std::FILE* file = nullptr;
  bool compressed = false;
  bool file_eof = false;
  bool zinit = false;
  bool stream_end = false;
  z_stream zs{};
  std::vector<uint8_t> in;
  int64_t produced = 0;  // bytes handed out so far (for messages)

  ~State() {
    if (zinit) inflateEnd(&zs);
    if (file != nullptr) std::fclose(file);
  }
};

InputStream::InputStream(std::unique_ptr<State> state) : state_(std::move(state)) {}
InputStream::InputStream(InputStream&&) noexcept = default;
InputStream& InputStream::operator=(InputStream&&) noexcept = default;
InputStream::~InputStream() = default;

absl::StatusOr<InputStream> InputStream::Open(const fs::path& path, int64_t offset,
                                              Compression compression) {
  DECIMA_ASSIGN_OR_RETURN(const int64_t size, RegularFileSize(path));
  if (offset < 0 || offset > size) {
    return Invalid(path, "data offset ", offset, " lies outside the file (", size, " bytes)");
  }
  auto st = std::make_unique<State>();
  st->path = path;
  st->file = std::fopen(path.c_str(), "rb");
  if (st->file == nullptr) {
    return absl::ErrnoToStatus(errno, absl::StrCat(path.string(), ": cannot open"));
  }
  if (fseeko(st->file, static_cast<off_t>(offset), SEEK_SET) != 0) {
    return Invalid(path, "cannot seek to byte ", offset);
  }
  if (compression == Compression::kZlibOrGzip) {
    st->compressed = true;
    st->in.resize(kInputChunk);
    // 15 + 32: maximum window, zlib or gzip header detected automatically.
    if (inflateInit2(&st->zs, 15 + 32) != Z_OK) {
      return absl::ResourceExhaustedError(absl::StrCat(path.string(), ": zlib init failed"));
    }
    st->zinit = true;
  }
  return InputStream(std::move(st));
}

absl::StatusOr<size_t> InputStream::ReadSome(uint8_t* dst, size_t n) {
  State& s = *state_;
  if (n == 0) return size_t{0};
  if (!s.compressed) {
    const size_t got = std::fread(dst, 1, n, s.file);
    if (got == 0 && std::ferror(s.file)) return Invalid(s.path, "read error");
    s.produced += static_cast<int64_t>(got);
    return got;
  }
  z_stream& zs = s.zs;
  while (true) {
    if (zs.avail_in == 0 && !s.file_eof) {
      const size_t got = std::fread(s.in.data(), 1, s.in.size(), s.file);
      if (got == 0) {
        if (std::ferror(s.file)) return Invalid(s.path, "read error");
        s.file_eof = true;
      }
      zs.next_in = s.in.data();
      zs.avail_in = static_cast<uInt>(got);
    }
    if (s.stream_end) {
      // Another gzip member may follow (gzip allows concatenation); anything else after the
      // end of the stream is ignored like gzip(1) does.
      if (zs.avail_in >= 2 && zs.next_in[0] == 0x1f && zs.next_in[1] == 0x8b) {
        inflateReset(&zs);
        s.stream_end = false;
      } else {
        return size_t{0};
      }
    }
    zs.next_out = dst;
    zs.avail_out = static_cast<uInt>(std::min<size_t>(n, 1u << 30));
    const uInt before = zs.avail_out;
    const int ret = inflate(&zs, Z_NO_FLUSH);
    const size_t got = before - zs.avail_out;
    s.produced += static_cast<int64_t>(got);
    if (ret == Z_STREAM_END) {
      s.stream_end = true;
      if (got > 0) return got;
      continue;
    }
    if (ret == Z_OK || ret == Z_BUF_ERROR) {
      if (got > 0) return got;
      if (zs.avail_in == 0 && s.file_eof) {
        return Invalid(s.path, "truncated: compressed stream ends after ", s.produced,
                       " decompressed bytes without its end marker");
      }
      continue;
    }
    return Invalid(s.path, "corrupt compressed data after ", s.produced,
                   " decompressed bytes (zlib error ", ret, zs.msg != nullptr ? ": " : "",
                   zs.msg != nullptr ? zs.msg : "", ")");
  }
}

absl::Status InputStream::ReadExact(void* dst, size_t n, absl::string_view what) {
  auto* p = static_cast<uint8_t*>(dst);
  size_t done = 0;
  while (done < n) {
    DECIMA_ASSIGN_OR_RETURN(const size_t got, ReadSome(p + done, n - done));
    if (got == 0) {
      return Invalid(state_->path, "truncated: ", what, " needs ", n, " bytes, only ", done,
                     " available");
    }
    done += got;
  }
  return absl::OkStatus();
}

absl::Status InputStream::Skip(int64_t n, absl::string_view what) {
  uint8_t buf[8192];
  while (n > 0) {
    const size_t chunk = static_cast<size_t>(std::min<int64_t>(n, sizeof(buf)));
    DECIMA_RETURN_IF_ERROR(ReadExact(buf, chunk, what));
    n -= static_cast<int64_t>(chunk);
  }
  return absl::OkStatus();
}

absl::Status InputStream::ReadInto(std::vector<uint8_t>& out, size_t n, absl::string_view what) {
  const size_t start = out.size();
  const size_t target = start + n;
  size_t filled = start;
  while (filled < target) {
    // Raw files were size-checked by the caller; compressed ones grow with the output.
    const size_t step = state_->compressed ? std::max(kGrowStep, filled - start) : n;
    out.resize(std::min(target, filled + step));
    while (filled < out.size()) {
      DECIMA_ASSIGN_OR_RETURN(const size_t got, ReadSome(out.data() + filled, out.size() - filled));
      if (got == 0) {
        const size_t have = filled - start;
        out.resize(filled);
        return Invalid(state_->path, "truncated: ", what, " needs ", n, " bytes, only ", have,
                       " available");
      }
      filled += got;
    }
  }
  return absl::OkStatus();
}

absl::Status InputStream::ExpectEnd(absl::string_view what) {
  uint8_t extra = 0;
  DECIMA_ASSIGN_OR_RETURN(const size_t got, ReadSome(&extra, 1));
  if (got != 0) {
    return Invalid(state_->path, what, ": more data than the header implies (the dimensions ",
                   "or type do not match the data size)");
  }
  return absl::OkStatus();
}

absl::Status CheckVoxelBytes(const fs::path& data_path, int64_t offset, bool compressed,
                             int64_t skip, int64_t nbytes, absl::string_view what) {
  DECIMA_ASSIGN_OR_RETURN(const int64_t size, RegularFileSize(data_path));
  if (offset < 0 || skip < 0 || offset > size) {
    return Invalid(data_path, "truncated: ", what, " starts at byte ", offset,
                   " but the file has only ", size, " bytes");
  }
  if (!compressed) {
    offset += skip;
    const int64_t avail = size - std::min(offset, size);
    if (avail < nbytes) {
      return Invalid(data_path, "truncated: ", what, " needs ", nbytes, " bytes from byte ", offset,
                     ", the file has only ", avail);
    }
    if (avail > nbytes) {
      return Invalid(data_path, what, ": the file has ", avail, " bytes from byte ", offset,
                     ", the header implies ", nbytes,
                     " (the dimensions or type do not match the data size)");
    }
  } else if ((nbytes + skip) / kMaxInflateRatio > size - offset) {
    return Invalid(data_path, "truncated: ", what, " needs ", nbytes, " bytes but only ",
                   size - offset, " compressed bytes are present (beyond zlib's maximum ratio)");
  }
  return absl::OkStatus();
}

absl::StatusOr<std::vector<uint8_t>> ReadVoxelBytes(const fs::path& data_path, int64_t offset,
                                                    bool compressed, int64_t skip, int64_t nbytes,
                                                    absl::string_view what) {
  DECIMA_RETURN_IF_ERROR(CheckVoxelBytes(data_path, offset, compressed, skip, nbytes, what));
  if (!compressed) offset += skip;  // raw data: `skip` bytes are simply not read
  DECIMA_ASSIGN_OR_RETURN(InputStream in,
                          InputStream::Open(data_path, offset,
                                            compressed ? InputStream::Compression::kZlibOrGzip
                                                       : InputStream::Compression::kNone));
  if (compressed) DECIMA_RETURN_IF_ERROR(in.Skip(skip, what));
  std::vector<uint8_t> out;
  DECIMA_RETURN_IF_ERROR(in.ReadInto(out, static_cast<size_t>(nbytes), what));
  if (compressed) DECIMA_RETURN_IF_ERROR(in.ExpectEnd(what));
  return out;
}

void SwapBytes(uint8_t* data, size_t count, size_t elem_size) {
  if (elem_size <= 1) return;
  for (size_t i = 0; i < count; ++i) std::reverse(data + i * elem_size, data + (i + 1) * elem_size);
}

absl::Status CheckDims(const fs::path& path, const std::array<int64_t, 3>& dims,
                       absl::string_view field) {
  for (int c = 0; c < 3; ++c) {
    if (dims[c] < 1) {
      return Invalid(path, field, "[", c, "] = ", dims[c], ", expected >= 2");
    }
  }
  for (int c = 0; c < 3; ++c) {
    if (dims[c] < 2) {
      return Invalid(path, "2D image: Decima needs a 3D volume (", field, "[", c, "] = ", dims[c],
                     "; every axis needs at least 2 voxels to be meshed)");
    }
  }
  if (dims[0] > kMaxVoxels / dims[1] || dims[0] * dims[1] > kMaxVoxels / dims[2]) {
    return Invalid(path, field, " ", dims[0], "x", dims[1], "x", dims[2], " exceeds the limit of ",
                   kMaxVoxels, " voxels");
  }
  return absl::OkStatus();
}

int64_t DataBytes(const std::array<int64_t, 3>& dims, VoxelType type) {
  return dims[0] * dims[1] * dims[2] * static_cast<int64_t>(VoxelTypeSize(type));
}

absl::StatusOr<fs::path> ResolveDataFile(const fs::path& header, absl::string_view name,
                                         absl::string_view field) {
  if (name.empty()) return Invalid(header, field, " is empty");
  const fs::path rel(std::string{name});
  if (rel.is_absolute() || rel.has_root_name() || rel.has_root_directory()) {
    return Invalid(header, field, " '", name,
                   "' is an absolute path; detached data must lie beside the header");
  }
  for (const auto& part : rel) {
    if (part == "..") {
      return Invalid(header, field, " '", name,
                     "' leaves the header's folder ('..'); detached data must lie beside it");
    }
  }
  return header.parent_path() / rel;
}

std::string LowerName(const fs::path& path) {
  std::string s = path.filename().string();
  for (char& c : s) c = static_cast<char>(std::tolower(static_cast<unsigned char>(c)));
  return s;
}

bool EndsWith(absl::string_view s, absl::string_view suffix) {
  return s.size() >= suffix.size() && s.substr(s.size() - suffix.size()) == suffix;
}

absl::StatusOr<std::vector<uint8_t>> Deflate(const std::vector<ByteSpan>& parts, bool gzip,
                                             int level, const fs::path& path) {
  if (level < 1 || level > 9) {
    return absl::InvalidArgumentError(
        absl::StrCat(path.string(), ": compression level ", level, ", expected 1..9"));
  }
  z_stream zs{};
  if (deflateInit2(&zs, level, Z_DEFLATED, gzip ? 15 + 16 : 15, 8, Z_DEFAULT_STRATEGY) != Z_OK) {
    return absl::ResourceExhaustedError(absl::StrCat(path.string(), ": zlib init failed"));
  }
  size_t total = 0;
  for (const auto& p : parts) total += p.size;
  std::vector<uint8_t> out(deflateBound(&zs, total) + 64);
  zs.next_out = out.data();
  size_t out_done = 0;
  for (size_t i = 0; i < parts.size(); ++i) {
    const auto* src = static_cast<const uint8_t*>(parts[i].data);
    size_t left = parts[i].size;
    const bool last = i + 1 == parts.size();
    do {
      const size_t chunk = std::min<size_t>(left, 1u << 30);
      zs.next_in = const_cast<Bytef*>(src);
      zs.avail_in = static_cast<uInt>(chunk);
      src += chunk;
      left -= chunk;
      const int flush = (last && left == 0) ? Z_FINISH : Z_NO_FLUSH;
      int ret;
      do {
        zs.next_out = out.data() + out_done;
        const size_t room = std::min<size_t>(out.size() - out_done, 1u << 30);
        zs.avail_out = static_cast<uInt>(room);
        ret = deflate(&zs, flush);
        out_done += room - zs.avail_out;
        if (ret == Z_STREAM_ERROR) break;
        if (zs.avail_out == 0 && out_done == out.size()) out.resize(out.size() * 2);
      } while (zs.avail_in > 0 || (flush == Z_FINISH && ret != Z_STREAM_END));
      if (ret == Z_STREAM_ERROR) {
        deflateEnd(&zs);
        return absl::InternalError(absl::StrCat(path.string(), ": zlib deflate failed"));
      }
    } while (left > 0);
  }
  if (parts.empty()) {
    zs.next_in = nullptr;
    zs.avail_in = 0;
    zs.next_out = out.data();
    zs.avail_out = static_cast<uInt>(out.size());
    deflate(&zs, Z_FINISH);
    out_done = out.size() - zs.avail_out;
  }
  deflateEnd(&zs);
  out.resize(out_done);
  return out;
}

}  // namespace decima::io::internal
