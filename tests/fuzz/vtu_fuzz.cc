// libFuzzer target for ReadVtu (clang, -DDECIMA_FUZZ=ON). Run from the build folder:
//   tests/fuzz/vtu_fuzz -max_len=65536 -rss_limit_mb=2048 CORPUS_COPY ../tests/fuzz/corpus/vtu
#include "tests/fuzz/fuzz_entries.h"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  return decima::fuzz::ReadVtuEntry(data, size);
}
