// libFuzzer target for the transfer-function JSON reader (clang, -DDECIMA_FUZZ=ON). Run:
//   tests/fuzz/transfer_function_fuzz -max_len=8192 CORPUS_COPY
//   ../tests/fuzz/corpus/transfer_function
#include "tests/fuzz/fuzz_entries.h"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  return decima::fuzz::TransferFunctionEntry(data, size);
}
