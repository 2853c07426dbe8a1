// libFuzzer target for the volume readers: the input bytes become a file whose format is picked
// by the first byte (.nii, .nii.gz, .mha, .nrrd, or no extension to exercise sniffing), then
// ReadVolume must return a Status - never crash, hang or allocate beyond the header checks.
// Build with clang (see CMakeLists.txt), run: ./io_fuzz -max_len=4096 -rss_limit_mb=2048
#include <unistd.h>

#include <cstdint>
#include <cstdio>
#include <filesystem>
#include <string>

#include "core/io/volume_io.h"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  if (size < 1) return 0;
  static const char* kExt[] = {".nii", ".nii.gz", ".mha", ".nrrd", ""};
  const std::string ext = kExt[data[0] % 5];
  const std::filesystem::path path = std::filesystem::temp_directory_path() /
                                     ("decima-io-fuzz-" + std::to_string(::getpid()) + ext);
  if (std::FILE* f = std::fopen(path.c_str(), "wb")) {
    std::fwrite(data + 1, 1, size - 1, f);
    std::fclose(f);
  }
  auto volume = decima::io::ReadVolume(path);
  (void)volume;
  std::filesystem::remove(path);
  return 0;
}
