// PNG files: 8-bit RGB / RGBA images for rendered pictures, difference maps and plots.
//
// libpng is used only here (DESIGN.md: image libraries stay inside core/io). Both functions are
// thread-safe (no shared state) and never throw.
#pragma once

#include <cstdint>
#include <filesystem>
#include <string>
#include <utility>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"

namespace decima {

// An 8-bit image, rows top to bottom, channels interleaved (RGB or RGBA).
struct Image {
  int width = 0;
  int height = 0;
  int channels = 0;             // 3 (RGB) or 4 (RGBA)
  std::vector<uint8_t> pixels;  // width * height * channels bytes
};

// Largest image ReadPng accepts (width * height), checked from the header before allocating.
inline constexpr int64_t kMaxPngPixels = int64_t{1} << 26;

// Writes `pixels` (width * height * channels bytes, rows top to bottom) as an 8-bit PNG.
// The file is written to a temporary name beside `path` and renamed, so readers never see a
// half-written file. Errors: InvalidArgument for a bad size, channel count (3 or 4) or null
// pixels; Internal/PermissionDenied-style errors (as absl codes) naming the file on I/O failure.
absl::Status WritePng(const std::filesystem::path& path, int width, int height, int channels,
                      const uint8_t* pixels);
absl::Status WritePng(const std::filesystem::path& path, const Image& image);

// The same with tEXt chunks (keyword, Latin-1 text) after the header, e.g. {"Software",
// "decima"}, {"decima:job", "jobs/abc"}: the parameters travel with the picture. Keywords are
// 1..79 printable characters (PNG spec 11.3.4.3); InvalidArgument otherwise.
absl::Status WritePng(const std::filesystem::path& path, const Image& image,
                      const std::vector<std::pair<std::string, std::string>>& text);
// Reads the tEXt chunks of a PNG file (keyword -> text); NotFound / InvalidArgument as ReadPng.
absl::StatusOr<std::vector<std::pair<std::string, std::string>>> ReadPngText(
    const std::filesystem::path& path);

// Reads any PNG libpng understands (gray, palette, 16-bit, with or without alpha) as 8-bit RGB,
// or RGBA when the file has an alpha channel or transparency. Errors: NotFound when the file
// does not exist, InvalidArgument naming the file and libpng's reason when it is not a valid
// PNG (truncated, bad signature, corrupt data) or larger than kMaxPngPixels.
absl::StatusOr<Image> ReadPng(const std::filesystem::path& path);

}  // namespace decima
