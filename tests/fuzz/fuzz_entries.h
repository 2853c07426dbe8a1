// The entry functions of the fuzz targets, shared by the libFuzzer binaries (clang,
// DECIMA_FUZZ=ON) and by fuzz_replay_test, which runs every seed of the corpora through them in
// the normal build. Each returns 0; a contract violation aborts (libFuzzer reports it as a crash,
// the replay test dies).
#pragma once

#include <cstddef>
#include <cstdint>

namespace decima::fuzz {

// The bytes as a .vtu file read by ReadVtu: it must return a Status, and a mesh it accepts must
// satisfy the TetMesh invariants ReadVtu promises (consistent sizes, indices in range, positive
// volumes, finite scalars, labels and regions < 8).
int ReadVtuEntry(const uint8_t* data, size_t size);

// The bytes as transfer-function JSON: ParseTransferFunction must return a Status, and a function
// it accepts must serialize (TransferFunctionToJson) to JSON it accepts again.
int TransferFunctionEntry(const uint8_t* data, size_t size);

}  // namespace decima::fuzz
