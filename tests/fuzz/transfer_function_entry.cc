#include <string>

#include "absl/strings/string_view.h"
#include "core/render/transfer_function.h"
#include "tests/fuzz/fuzz_entries.h"
#include "tests/fuzz/fuzz_require.h"

namespace decima::fuzz {

int TransferFunctionEntry(const uint8_t* data, size_t size) {
  const absl::string_view json(reinterpret_cast<const char*>(data), size);
  const ScalarRange range{-1024, 3071};
  auto tf = ParseTransferFunction(json, range, "fuzz input");
  if (!tf.ok()) return 0;
  auto again = ParseTransferFunction(TransferFunctionToJson(*tf), range, "round trip");
  Require(again.ok(), "an accepted transfer function serializes to JSON that parses again");
  return 0;
}

}  // namespace decima::fuzz
