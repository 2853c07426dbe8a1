#include "core/io/png.h"

#include <png.h>
#include <unistd.h>

#include <zlib.h>

#include <cstring>
#include <fstream>
#include <sstream>
#include <system_error>

#include "absl/strings/str_cat.h"
#include "core/common/status.h"

namespace decima {
namespace {

// libpng's simplified API (png_image_*) reports errors through image.message instead of
// longjmp, so no setjmp crosses C++ frames here.
std::string Message(const png_image& image) {
  return image.message[0] != '\0' ? std::string(image.message) : std::string("unknown error");
}

}  // namespace

absl::Status WritePng(const std::filesystem::path& path, int width, int height, int channels,
                      const uint8_t* pixels) {
  if (width <= 0 || height <= 0 || int64_t{width} * height > kMaxPngPixels) {
    return absl::InvalidArgumentError(absl::StrCat("WritePng ", path.string(), ": size ", width,
                                                   "x", height, " is not in 1..2^26 pixels"));
  }
  if (channels != 3 && channels != 4) {
    return absl::InvalidArgumentError(absl::StrCat("WritePng ", path.string(), ": channels is ",
                                                   channels, ", expected 3 (RGB) or 4 (RGBA)"));
  }
  if (pixels == nullptr) {
    return absl::InvalidArgumentError(absl::StrCat("WritePng ", path.string(), ": no pixels"));
  }
  png_image image;
  std::memset(&image, 0, sizeof(image));
  image.version = PNG_IMAGE_VERSION;
  image.width = static_cast<png_uint_32>(width);
  image.height = static_cast<png_uint_32>(height);
  image.format = channels == 4 ? PNG_FORMAT_RGBA : PNG_FORMAT_RGB;

  // Temporary name in the same folder, so the rename is atomic on POSIX file systems.
  std::filesystem::path tmp = path;
  tmp += absl::StrCat(".tmp", ::getpid());
  if (!png_image_write_to_file(&image, tmp.c_str(), /*convert_to_8bit=*/0, pixels,
                               /*row_stride=*/width * channels, /*colormap=*/nullptr)) {
    const std::string why = Message(image);
    png_image_free(&image);
    std::error_code ignored;
    std::filesystem::remove(tmp, ignored);
    return absl::InternalError(absl::StrCat("WritePng ", path.string(), ": ", why));
  }
  std::error_code ec;
  std::filesystem::rename(tmp, path, ec);
  if (ec) {
    std::error_code ignored;
    std::filesystem::remove(tmp, ignored);
    return absl::InternalError(
        absl::StrCat("WritePng ", path.string(), ": cannot rename temporary file: ", ec.message()));
  }
  return absl::OkStatus();
}

absl::Status WritePng(const std::filesystem::path& path, const Image& image) {
  if (image.pixels.size() != size_t(image.width) * size_t(std::max(0, image.height)) *
                                 size_t(std::max(0, image.channels)) ||
      image.width <= 0) {
    return absl::InvalidArgumentError(absl::StrCat("WritePng ", path.string(),
                                                   ": pixel buffer holds ", image.pixels.size(),
                                                   " bytes, expected width * height * channels"));
  }
  return WritePng(path, image.width, image.height, image.channels, image.pixels.data());
}

absl::StatusOr<Image> ReadPng(const std::filesystem::path& path) {
  std::error_code ec;
  if (!std::filesystem::is_regular_file(path, ec)) {
    return absl::NotFoundError(absl::StrCat("ReadPng ", path.string(), ": no such file"));
  }
  png_image image;
  std::memset(&image, 0, sizeof(image));
  image.version = PNG_IMAGE_VERSION;
  if (!png_image_begin_read_from_file(&image, path.c_str())) {
    const std::string why = Message(image);
    png_image_free(&image);
    return absl::InvalidArgumentError(
        absl::StrCat("ReadPng ", path.string(), ": not a valid PNG (", why, ")"));
  }
  if (int64_t{image.width} * image.height > kMaxPngPixels) {
    const std::string dims = absl::StrCat(image.width, "x", image.height);
    png_image_free(&image);
    return absl::InvalidArgumentError(
        absl::StrCat("ReadPng ", path.string(), ": ", dims, " exceeds the 2^26 pixel limit"));
  }
  const bool alpha = (image.format & PNG_FORMAT_FLAG_ALPHA) != 0;
  image.format = alpha ? PNG_FORMAT_RGBA : PNG_FORMAT_RGB;
  Image out;
  out.width = static_cast<int>(image.width);
  out.height = static_cast<int>(image.height);
  out.channels = alpha ? 4 : 3;
  out.pixels.resize(PNG_IMAGE_SIZE(image));
  if (!png_image_finish_read(&image, /*background=*/nullptr, out.pixels.data(),
                             /*row_stride=*/0, /*colormap=*/nullptr)) {
    const std::string why = Message(image);
    png_image_free(&image);
    return absl::InvalidArgumentError(
        absl::StrCat("ReadPng ", path.string(), ": corrupt PNG data (", why, ")"));
  }
  return out;
}

}  // namespace decima

namespace decima {
namespace {

void PutU32(std::string* s, uint32_t v) {
  for (int k = 3; k >= 0; --k) s->push_back(static_cast<char>((v >> (8 * k)) & 0xff));
}

uint32_t GetU32(const std::string& s, size_t at) {
  uint32_t v = 0;
  for (int k = 0; k < 4; ++k) v = (v << 8) | static_cast<unsigned char>(s[at + k]);
  return v;
}

}  // namespace

absl::Status WritePng(const std::filesystem::path& path, const Image& image,
                      const std::vector<std::pair<std::string, std::string>>& text) {
  for (const auto& [key, value] : text) {
    bool ok = !key.empty() && key.size() <= 79 && key.front() != ' ' && key.back() != ' ';
    for (unsigned char c : key) ok = ok && c >= 32 && c != 127;
    if (!ok) {
      return absl::InvalidArgumentError(
          absl::StrCat("WritePng ", path.string(), ": text keyword '", key,
                       "' is not 1..79 printable characters without leading/trailing space"));
    }
    if (value.find('\0') != std::string::npos) {
      return absl::InvalidArgumentError(
          absl::StrCat("WritePng ", path.string(), ": text of '", key, "' holds a NUL byte"));
    }
  }
  // Encoded in memory by the simplified API (no longjmp), then the chunks are spliced in after
  // IHDR (8-byte signature + 25-byte IHDR chunk), which the PNG spec allows for tEXt.
  std::filesystem::path tmp = path;
  tmp += absl::StrCat(".tmp", ::getpid(), "t");
  DECIMA_RETURN_IF_ERROR(WritePng(tmp, image));
  std::string bytes;
  {
    std::ifstream in(tmp, std::ios::binary);
    std::stringstream ss;
    ss << in.rdbuf();
    bytes = ss.str();
  }
  std::error_code ec;
  std::filesystem::remove(tmp, ec);
  if (bytes.size() < 33)
    return absl::InternalError(absl::StrCat("WritePng ", path.string(), ": short"));
  std::string chunks;
  for (const auto& [key, value] : text) {
    const std::string data = key + std::string(1, '\0') + value;
    PutU32(&chunks, static_cast<uint32_t>(data.size()));
    const std::string body = "tEXt" + data;
    chunks += body;
    PutU32(&chunks, static_cast<uint32_t>(
                        crc32(0, reinterpret_cast<const Bytef*>(body.data()), body.size())));
  }
  bytes.insert(33, chunks);
  std::filesystem::path tmp2 = path;
  tmp2 += absl::StrCat(".tmp", ::getpid());
  {
    std::ofstream out(tmp2, std::ios::binary | std::ios::trunc);
    out.write(bytes.data(), static_cast<std::streamsize>(bytes.size()));
    if (!out.good()) {
      return absl::InternalError(absl::StrCat("WritePng ", path.string(), ": write failed"));
    }
  }
  std::filesystem::rename(tmp2, path, ec);
  if (ec) {
    std::filesystem::remove(tmp2, ec);
    return absl::InternalError(absl::StrCat("WritePng ", path.string(), ": rename failed"));
  }
  return absl::OkStatus();
}

absl::StatusOr<std::vector<std::pair<std::string, std::string>>> ReadPngText(
    const std::filesystem::path& path) {
  std::ifstream in(path, std::ios::binary);
  if (!in) return absl::NotFoundError(absl::StrCat("ReadPngText ", path.string(), ": cannot open"));
  std::stringstream ss;
  ss << in.rdbuf();
  const std::string b = ss.str();
  if (b.size() < 8 || b.compare(0, 8, "\x89PNG\r\n\x1a\n") != 0) {
    return absl::InvalidArgumentError(absl::StrCat("ReadPngText ", path.string(), ": not a PNG"));
  }
  std::vector<std::pair<std::string, std::string>> out;
  size_t at = 8;
  while (at + 12 <= b.size()) {
    const uint32_t len = GetU32(b, at);
    if (len > b.size() - at - 12) {
      return absl::InvalidArgumentError(
          absl::StrCat("ReadPngText ", path.string(), ": chunk at ", at, " runs past the end"));
    }
    const std::string type = b.substr(at + 4, 4);
    if (type == "tEXt") {
      const std::string data = b.substr(at + 8, len);
      const size_t nul = data.find('\0');
      if (nul != std::string::npos) out.emplace_back(data.substr(0, nul), data.substr(nul + 1));
    }
    if (type == "IEND") break;
    at += 12 + len;
  }
  return out;
}

}  // namespace decima
