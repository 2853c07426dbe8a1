// The libFuzzer main of one entry of fuzz_entries.h, chosen at compile time
// (DECIMA_FUZZ_ENTRY=NiftiEntry, ...); see CMakeLists.txt and README.md for how to run them.
#include "tests/fuzz/fuzz_entries.h"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  return decima::fuzz::DECIMA_FUZZ_ENTRY(data, size);
}
