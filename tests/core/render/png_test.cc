// core/io/png: round trips, and every broken file gives a clear error (never a crash).
#include "core/io/png.h"

#include <gtest/gtest.h>
#include <zlib.h>

#include <fstream>
#include <iterator>
#include <string>

#include "tests/testing/test_data.h"

namespace decima {
namespace {

Image Pattern(int w, int h, int channels) {
  Image im{w, h, channels, std::vector<uint8_t>(size_t(w) * h * channels)};
  for (size_t i = 0; i < im.pixels.size(); ++i) im.pixels[i] = static_cast<uint8_t>(i * 37 + i / 7);
  return im;
}

std::string Slurp(const std::filesystem::path& p) {
  std::ifstream in(p, std::ios::binary);
  return {std::istreambuf_iterator<char>(in), {}};
}

void Spit(const std::filesystem::path& p, const std::string& bytes) {
  std::ofstream(p, std::ios::binary) << bytes;
}

void ExpectInvalid(const std::filesystem::path& p, const std::string& words) {
  auto im = ReadPng(p);
  ASSERT_FALSE(im.ok()) << p;
  EXPECT_EQ(im.status().code(), absl::StatusCode::kInvalidArgument) << im.status();
  EXPECT_NE(im.status().message().find(p.filename().string()), std::string::npos) << im.status();
  EXPECT_NE(im.status().message().find(words), std::string::npos) << im.status();
}

TEST(Png, RgbAndRgbaRoundTripExactly) {
  const auto dir = testing::MakeScratchDir("png");
  for (int channels : {3, 4}) {
    const Image im = Pattern(37, 11, channels);
    const auto path = dir / (channels == 3 ? "rgb.png" : "rgba.png");
    ASSERT_TRUE(WritePng(path, im).ok());
    auto back = ReadPng(path);
    ASSERT_TRUE(back.ok()) << back.status();
    EXPECT_EQ(back->width, 37);
    EXPECT_EQ(back->height, 11);
    EXPECT_EQ(back->channels, channels);
    EXPECT_EQ(back->pixels, im.pixels);
  }
  // No temporary file is left behind.
  int files = 0;
  for (const auto& e : std::filesystem::directory_iterator(dir)) files += e.is_regular_file();
  EXPECT_EQ(files, 2);
}

TEST(Png, WriteRejectsBadImages) {
  const auto dir = testing::MakeScratchDir("png-w");
  Image im = Pattern(4, 4, 3);
  im.channels = 2;
  im.pixels.resize(32);
  EXPECT_EQ(WritePng(dir / "a.png", im).code(), absl::StatusCode::kInvalidArgument);
  im = Pattern(4, 4, 3);
  im.pixels.pop_back();
  EXPECT_EQ(WritePng(dir / "b.png", im).code(), absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(WritePng(dir / "c.png", 0, 4, 3, im.pixels.data()).code(),
            absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(WritePng(dir / "d.png", 4, 4, 3, nullptr).code(), absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(WritePng(dir / "e.png", 1 << 14, 1 << 14, 3, im.pixels.data()).code(),
            absl::StatusCode::kInvalidArgument);
  // Unwritable destination: a folder that does not exist.
  const absl::Status s = WritePng(dir / "no" / "such" / "f.png", Pattern(4, 4, 3));
  EXPECT_FALSE(s.ok());
  EXPECT_NE(s.message().find("f.png"), std::string::npos) << s;
}

TEST(Png, BrokenFilesGiveClearErrors) {
  const auto dir = testing::MakeScratchDir("png-r");
  EXPECT_EQ(ReadPng(dir / "missing.png").status().code(), absl::StatusCode::kNotFound);
  EXPECT_EQ(ReadPng(dir).status().code(), absl::StatusCode::kNotFound);  // a folder

  Spit(dir / "zero.png", "");
  ExpectInvalid(dir / "zero.png", "not a valid PNG");
  Spit(dir / "text.png", "this is not a PNG file, just some text\n");
  ExpectInvalid(dir / "text.png", "not a valid PNG");
  Spit(dir / "sig.png", std::string("\x89PNG\r\n\x1a\n", 8));
  ExpectInvalid(dir / "sig.png", "not a valid PNG");

  ASSERT_TRUE(WritePng(dir / "good.png", Pattern(64, 64, 3)).ok());
  const std::string good = Slurp(dir / "good.png");
  // Truncated in the header, in the image data, and just before the end.
  for (size_t keep : {size_t{20}, good.size() / 2, good.size() - 13}) {
    const auto p = dir / ("trunc" + std::to_string(keep) + ".png");
    Spit(p, good.substr(0, keep));
    auto im = ReadPng(p);
    ASSERT_FALSE(im.ok()) << keep;
    EXPECT_EQ(im.status().code(), absl::StatusCode::kInvalidArgument) << im.status();
  }
  // Corrupt image data (CRC mismatch in IDAT).
  std::string corrupt = good;
  corrupt[good.size() / 2] ^= 0x5a;
  Spit(dir / "corrupt.png", corrupt);
  EXPECT_FALSE(ReadPng(dir / "corrupt.png").ok());
}

TEST(Png, HugeDimensionsAreRejectedBeforeAllocating) {
  const auto dir = testing::MakeScratchDir("png-h");
  ASSERT_TRUE(WritePng(dir / "small.png", Pattern(8, 8, 3)).ok());
  std::string bytes = Slurp(dir / "small.png");
  // IHDR data starts at byte 16 (signature 8, length 4, type 4): width, height big-endian.
  auto put32 = [&](size_t at, uint32_t v) {
    for (int k = 0; k < 4; ++k) bytes[at + k] = static_cast<char>((v >> (24 - 8 * k)) & 0xff);
  };
  put32(16, 60000);
  put32(20, 60000);
  const uLong crc = crc32(0, reinterpret_cast<const Bytef*>(bytes.data() + 12), 17);
  put32(29, static_cast<uint32_t>(crc));
  Spit(dir / "huge.png", bytes);
  ExpectInvalid(dir / "huge.png", "exceeds the 2^26 pixel limit");
}

TEST(Png, TextChunksTravelWithThePictureAndLibpngStillReadsIt) {
  const auto dir = testing::MakeScratchDir("png-t");
  const Image im = Pattern(16, 8, 3);
  const std::vector<std::pair<std::string, std::string>> text = {
      {"Software", "decima"}, {"decima:view", "30:20"}, {"decima:job", "jobs/abc"}};
  ASSERT_TRUE(WritePng(dir / "t.png", im, text).ok());
  auto back = ReadPng(dir / "t.png");  // libpng checks the CRCs of the spliced chunks
  ASSERT_TRUE(back.ok()) << back.status();
  EXPECT_EQ(back->pixels, im.pixels);
  auto read = ReadPngText(dir / "t.png");
  ASSERT_TRUE(read.ok()) << read.status();
  EXPECT_EQ(*read, text);
  EXPECT_EQ(WritePng(dir / "bad.png", im, {{"", "x"}}).code(), absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(WritePng(dir / "bad.png", im, {{std::string(80, 'k'), "x"}}).code(),
            absl::StatusCode::kInvalidArgument);
}

}  // namespace
}  // namespace decima
