// libFuzzer target for the volume readers: the input bytes become a file whose format is picked
// by the first byte (.nii, .nii.gz, .mha, .nrrd, or no extension to exercise sniffing), then
// ReadVolume and ProbeVolume must return a Status - never crash, hang or allocate beyond the
// header checks - and agree: a file ReadVolume accepts is one ProbeVolume accepts, with the same
// dimensions (the server decides on the probe alone).
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
  auto probe = decima::io::ProbeVolume(path);
  auto volume = decima::io::ReadVolume(path);
  std::filesystem::remove(path);
  if (volume.ok()) {
    if (!probe.ok() || (probe->parsed && probe->dims != volume->dims)) __builtin_trap();
  }
  return 0;
}
