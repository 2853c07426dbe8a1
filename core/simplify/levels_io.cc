#include "core/simplify/levels_io.h"

#include <zlib.h>

#include <algorithm>
#include <bit>
#include <cstring>
#include <fstream>
#include <limits>
#include <vector>

#include "absl/strings/str_cat.h"
#include "core/common/atomic_file.h"
#include "core/common/status.h"
#include "core/simplify/levels.h"

namespace decima {
namespace {

static_assert(std::endian::native == std::endian::little,
              "the .levels format is little-endian; this writer stores words as they are");

constexpr size_t kHeaderBytes = 64;
constexpr size_t kTrailerBytes = 8;
// Bytes per collapse in the inflated payload: removed vertex (i32), survivor - removed vertex
// (i32), cells deleted (u16).
constexpr uint64_t kCollapseBytes = 10;
// zlib inflates at most ~1032:1; a payload claiming more is not a zlib stream of its counts.
constexpr uint64_t kMaxInflateRatio = 1100;

// Murmur-style word mixing: fast enough for a 37 M-cell mesh (~0.2 s), and any changed word
// changes the digest with overwhelming probability. Not a cryptographic hash: it guards against
// accidents (a record applied to another mesh, a damaged file), not against forgery.
struct Digest {
  uint64_t h = 0x9e3779b97f4a7c15ull;
  void Words(const void* data, size_t bytes) {
    const auto* p = static_cast<const unsigned char*>(data);
    size_t i = 0;
    for (; i + 8 <= bytes; i += 8) {
      uint64_t w;
      std::memcpy(&w, p + i, 8);
      Mix(w);
    }
    uint64_t tail = 0;
    if (i < bytes) {
      std::memcpy(&tail, p + i, bytes - i);
      Mix(tail ^ (uint64_t(bytes - i) << 56));
    }
    Mix(bytes);
  }
  void Mix(uint64_t w) {
    w *= 0x87c37b91114253d5ull;
    w = std::rotl(w, 31);
    w *= 0x4cf5ad432745937full;
    h ^= w;
    h = std::rotl(h, 27) * 5 + 0x52dce729;
  }
  uint64_t Final() const {
    uint64_t x = h;
    x ^= x >> 33;
    x *= 0xff51afd7ed558ccdull;
    x ^= x >> 33;
    x *= 0xc4ceb9fe1a85ec53ull;
    x ^= x >> 33;
    return x;
  }
};

template <typename T>
void Put(std::string* out, T v) {
  char b[sizeof(T)];
  std::memcpy(b, &v, sizeof(T));
  out->append(b, sizeof(T));
}

template <typename T>
T Get(std::string_view bytes, size_t at) {
  T v;
  std::memcpy(&v, bytes.data() + at, sizeof(T));
  return v;
}

}  // namespace

uint64_t LevelsChecksum(std::string_view bytes) {
  Digest d;
  d.Words(bytes.data(), bytes.size());
  return d.Final();
}

uint64_t BaseMeshDigest(const TetMesh& m) {
  Digest d;
  auto add = [&](const auto& v) { d.Words(v.data(), v.size() * sizeof(v[0])); };
  add(m.positions);
  add(m.scalars);
  add(m.labels);
  add(m.interface_distance);
  add(m.vertex_flags);
  add(m.tets);
  return d.Final();
}

std::string SerializeLevels(const SimplifyLevels& levels, int compression) {
  const size_t n = levels.removed_vertex.size();
  std::vector<unsigned char> raw(n * kCollapseBytes);
  unsigned char* p = raw.data();
  for (size_t i = 0; i < n; ++i, p += 4) std::memcpy(p, &levels.removed_vertex[i], 4);
  for (size_t i = 0; i < n; ++i, p += 4) {
    // A survivor is a neighbour of the vertex it absorbs: the difference is small and repeats.
    const int32_t delta =
        int32_t(uint32_t(levels.survivor[i]) - uint32_t(levels.removed_vertex[i]));
    std::memcpy(p, &delta, 4);
  }
  for (size_t i = 0; i < n; ++i, p += 2) std::memcpy(p, &levels.cells_deleted[i], 2);
  uLongf packed_len = compressBound(uLong(raw.size()));
  std::vector<unsigned char> packed(packed_len);
  // compress2 fails only for lack of memory or a bad level; the level is clamped to zlib's range.
  if (compress2(packed.data(), &packed_len, raw.data(), uLong(raw.size()),
                std::clamp(compression, 1, 9)) != Z_OK) {
    packed_len = 0;
  }
  std::string out;
  out.reserve(kHeaderBytes + packed_len + kTrailerBytes);
  out.append(kLevelsMagic, sizeof kLevelsMagic);
  Put<uint32_t>(&out, kLevelsVersion);
  Put<uint32_t>(&out, levels.exhausted ? 1u : 0u);
  Put<uint64_t>(&out, uint64_t(levels.base_vertices));
  Put<uint64_t>(&out, uint64_t(levels.base_cells));
  Put<uint64_t>(&out, uint64_t(n));
  Put<uint32_t>(&out, uint32_t(levels.refit_iterations));
  Put<uint32_t>(&out, 0);
  Put<uint64_t>(&out, levels.base_digest);
  Put<uint64_t>(&out, uint64_t(packed_len));
  out.append(reinterpret_cast<const char*>(packed.data()), packed_len);
  Put<uint64_t>(&out, LevelsChecksum(out));
  return out;
}

absl::StatusOr<SimplifyLevels> ParseLevels(std::string_view bytes, std::string_view name) {
  auto bad = [&](const std::string& what) {
    return absl::InvalidArgumentError(
        absl::StrCat(std::string(name), ": not a level record: ", what));
  };
  if (bytes.size() < kHeaderBytes + kTrailerBytes) {
    return bad(absl::StrCat(bytes.size(), " bytes, shorter than the ", kHeaderBytes + kTrailerBytes,
                            " of header and checksum"));
  }
  if (std::memcmp(bytes.data(), kLevelsMagic, sizeof kLevelsMagic) != 0) {
    return bad("the file does not start with DECIMALV");
  }
  const uint32_t version = Get<uint32_t>(bytes, 8);
  if (version != kLevelsVersion) {
    return bad(absl::StrCat("version ", version, ", this reader knows version ", kLevelsVersion));
  }
  const uint32_t flags = Get<uint32_t>(bytes, 12);
  const uint64_t nv = Get<uint64_t>(bytes, 16), nt = Get<uint64_t>(bytes, 24),
                 n = Get<uint64_t>(bytes, 32);
  const uint32_t refit = Get<uint32_t>(bytes, 40), reserved = Get<uint32_t>(bytes, 44);
  const uint64_t digest = Get<uint64_t>(bytes, 48), packed_len = Get<uint64_t>(bytes, 56);
  if (flags > 1 || reserved != 0) {
    return bad(absl::StrCat("flags ", flags, " and reserved word ", reserved,
                            ": expected flags 0 or 1 and 0"));
  }
  if (nv > uint64_t(std::numeric_limits<int32_t>::max()) || nt > (uint64_t{1} << 40) || n > nv) {
    return bad(absl::StrCat(nv, " base vertices, ", nt, " base cells, ", n,
                            " collapses: expected vertices < 2^31, cells <= 2^40, collapses <= "
                            "vertices"));
  }
  if (packed_len != bytes.size() - kHeaderBytes - kTrailerBytes) {
    return bad(absl::StrCat("payload of ", packed_len, " bytes in a file of ", bytes.size(),
                            ": expected the file size less ", kHeaderBytes + kTrailerBytes));
  }
  const uint64_t stored = Get<uint64_t>(bytes, bytes.size() - kTrailerBytes);
  if (stored != LevelsChecksum(bytes.substr(0, bytes.size() - kTrailerBytes))) {
    return bad("checksum mismatch (the file is damaged or was changed)");
  }
  const uint64_t raw_len = n * kCollapseBytes;
  if (raw_len > packed_len * kMaxInflateRatio + 64) {
    return bad(absl::StrCat(n, " collapses cannot come from a payload of ", packed_len, " bytes"));
  }
  std::vector<unsigned char> raw(raw_len);
  uLongf got = uLongf(raw_len);
  const int z =
      uncompress(raw.data(), &got, reinterpret_cast<const Bytef*>(bytes.data() + kHeaderBytes),
                 uLong(packed_len));
  if (z != Z_OK || got != raw_len) {
    return bad(absl::StrCat("the payload does not inflate to ", raw_len, " bytes for ", n,
                            " collapses (zlib: ", zError(z), ")"));
  }
  SimplifyLevels levels;
  levels.base_vertices = int64_t(nv);
  levels.base_cells = int64_t(nt);
  levels.refit_iterations = int32_t(std::min<uint32_t>(refit, 1u << 30));
  levels.exhausted = flags & 1;
  levels.base_digest = digest;
  levels.removed_vertex.resize(n);
  levels.survivor.resize(n);
  levels.cells_deleted.resize(n);
  const unsigned char* p = raw.data();
  for (size_t i = 0; i < n; ++i, p += 4) std::memcpy(&levels.removed_vertex[i], p, 4);
  for (size_t i = 0; i < n; ++i, p += 4) {
    int32_t delta;
    std::memcpy(&delta, p, 4);
    levels.survivor[i] = int32_t(uint32_t(levels.removed_vertex[i]) + uint32_t(delta));
  }
  for (size_t i = 0; i < n; ++i, p += 2) std::memcpy(&levels.cells_deleted[i], p, 2);
  if (absl::Status s = ValidateLevels(levels); !s.ok()) {
    return bad(std::string(s.message()));
  }
  return levels;
}

absl::Status WriteLevels(const SimplifyLevels& levels, const std::filesystem::path& path) {
  AtomicFile file;
  DECIMA_RETURN_IF_ERROR(file.Open(path));
  DECIMA_RETURN_IF_ERROR(file.Write(SerializeLevels(levels)));
  return file.Commit();
}

absl::StatusOr<SimplifyLevels> ReadLevels(const std::filesystem::path& path) {
  std::ifstream in(path, std::ios::binary);
  if (!in) return absl::NotFoundError(absl::StrCat(path.string(), ": cannot open"));
  std::string bytes((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
  if (in.bad()) return absl::DataLossError(absl::StrCat(path.string(), ": read failed"));
  return ParseLevels(bytes, path.string());
}

}  // namespace decima
