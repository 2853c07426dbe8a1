#include "core/io/png.h"

#include <png.h>
#include <unistd.h>

#include <cstring>
#include <system_error>

#include "absl/strings/str_cat.h"

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
