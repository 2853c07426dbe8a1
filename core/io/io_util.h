// Internal helpers shared by the format readers and writers of core/io (not a public API).
//
// Invariants: every helper returns errors whose message starts with the file path; nothing
// here allocates more than the caller asked for, and compressed input is inflated into a buffer
// that grows with the data actually produced, never ahead of it beyond the caller's bound.
#pragma once

#include <array>
#include <bit>
#include <cstdint>
#include <cstdio>
#include <filesystem>
#include <memory>
#include <string>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/string_view.h"
#include "core/volume/volume.h"

namespace decima::io::internal {

static_assert(std::endian::native == std::endian::little,
              "core/io assumes a little-endian host (readers swap big-endian files)");

// "<path>: <message>" as InvalidArgument / Unimplemented.
template <typename... Args>
absl::Status Invalid(const std::filesystem::path& path, const Args&... args) {
  return absl::InvalidArgumentError(absl::StrCat(path.string(), ": ", args...));
}
template <typename... Args>
absl::Status Unsupported(const std::filesystem::path& path, const Args&... args) {
  return absl::UnimplementedError(absl::StrCat(path.string(), ": ", args...));
}

// NotFound if `path` does not exist, InvalidArgument if it is not a regular file; else its size.
absl::StatusOr<int64_t> RegularFileSize(const std::filesystem::path& path);

// The first min(max_bytes, size) bytes of the file.
absl::StatusOr<std::string> ReadFileHead(const std::filesystem::path& path, size_t max_bytes);

// True if the file starts with the gzip magic 1f 8b.
bool HasGzipMagic(absl::string_view head);

// Sequential reader over a file from a byte offset, either raw or through zlib inflate
// (zlib or gzip wrapper detected automatically; concatenated gzip members are followed).
class InputStream {
 public:
  enum class Compression { kNone, kZlibOrGzip };
  static absl::StatusOr<InputStream> Open(const std::filesystem::path& path, int64_t offset,
                                          Compression compression);
  InputStream(InputStream&&) noexcept;
  InputStream& operator=(InputStream&&) noexcept;
  ~InputStream();

  // Reads exactly `n` bytes into dst; a short read is InvalidArgument "truncated: <what> needs
  // N bytes, only M available", a corrupt stream is InvalidArgument naming zlib's message.
  absl::Status ReadExact(void* dst, size_t n, absl::string_view what);
  // Discards `n` bytes (same errors as ReadExact).
  absl::Status Skip(int64_t n, absl::string_view what);
  // Appends exactly `n` bytes to `out`, growing it in steps as data arrives (so a lying header
  // cannot make us allocate the whole claimed size for a short stream).
  absl::Status ReadInto(std::vector<uint8_t>& out, size_t n, absl::string_view what);
  // OK if no byte follows, else InvalidArgument "<what>: more data than the header implies".
  absl::Status ExpectEnd(absl::string_view what);

 private:
  struct State;
  explicit InputStream(std::unique_ptr<State> state);
  // Up to n bytes; 0 only at end of data. Errors on corrupt compressed data.
  absl::StatusOr<size_t> ReadSome(uint8_t* dst, size_t n);
  std::unique_ptr<State> state_;
};

// Reads `nbytes` of voxel data from `data_path`: raw data starts at byte `offset + skip`;
// compressed data is a zlib/gzip stream starting at byte `offset` whose first `skip` inflated
// bytes are discarded. Before allocating, checks that the file can hold the data: raw data
// must fill the file exactly to its end; compressed data must fit zlib's maximum ratio
// (1032:1) of the compressed bytes. Afterwards checks that no data follows. `what` names the
// data in errors.
absl::StatusOr<std::vector<uint8_t>> ReadVoxelBytes(const std::filesystem::path& data_path,
                                                    int64_t offset, bool compressed, int64_t skip,
                                                    int64_t nbytes, absl::string_view what);

// The checks ReadVoxelBytes makes before reading anything: the file holds exactly the raw data,
// or enough compressed bytes for it. What a header-only probe can know about the data.
absl::Status CheckVoxelBytes(const std::filesystem::path& data_path, int64_t offset,
                             bool compressed, int64_t skip, int64_t nbytes, absl::string_view what);

// How far a reader goes: the whole volume, or the header and the data size checks only
// (ProbeVolume: no voxel is read, so time and memory stay bounded whatever the header claims).
enum class ReadMode { kVolume, kHeaderOnly };

// The readers of volume_io.h with a mode; kHeaderOnly returns the Volume's geometry, type and
// modality with no voxel bytes.
absl::StatusOr<Volume> ReadNifti(const std::filesystem::path& path, ReadMode mode);
absl::StatusOr<Volume> ReadMetaImage(const std::filesystem::path& path, ReadMode mode);
absl::StatusOr<Volume> ReadNrrd(const std::filesystem::path& path, ReadMode mode);

// Reverses the byte order of `count` elements of `elem_size` bytes in place.
void SwapBytes(uint8_t* data, size_t count, size_t elem_size);

// dims must be >= 2 each (a volume needs two voxels per axis to be meshed) and the product
// <= kMaxVoxels. `field` names the header field in errors ("dim[1..3]", "DimSize", "sizes").
absl::Status CheckDims(const std::filesystem::path& path, const std::array<int64_t, 3>& dims,
                       absl::string_view field);

// The voxel count times the type size; callers ran CheckDims first.
int64_t DataBytes(const std::array<int64_t, 3>& dims, VoxelType type);

// Resolves a detached data file name from a header: must be relative, without "..", and
// resolves inside the header's folder.
absl::StatusOr<std::filesystem::path> ResolveDataFile(const std::filesystem::path& header,
                                                      absl::string_view name,
                                                      absl::string_view field);

// Lower-cased file name (for extension checks).
std::string LowerName(const std::filesystem::path& path);
bool EndsWith(absl::string_view s, absl::string_view suffix);

// zlib deflate of the concatenation of `parts` (gzip wrapper if `gzip`, zlib wrapper else).
struct ByteSpan {
  const void* data;
  size_t size;
};
absl::StatusOr<std::vector<uint8_t>> Deflate(const std::vector<ByteSpan>& parts, bool gzip,
                                             int level, const std::filesystem::path& path);

}  // namespace decima::io::internal
