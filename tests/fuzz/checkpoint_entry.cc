#include <unistd.h>

#include <filesystem>
#include <fstream>
#include <string>

#include "core/pipeline/checkpoint.h"
#include "tests/fuzz/fuzz_entries.h"
#include "tests/fuzz/fuzz_require.h"

namespace decima::fuzz {
namespace {

// A parsed payload must satisfy what RunJob relies on, and serialize back to the same bytes
// (the format has one encoding per value, so a resumed job sees exactly what was saved).
void CheckPayload(bool simplify, const std::string& payload) {
  if (simplify) {
    auto s = pipeline::ParseSimplifyResult(payload);
    if (!s.ok()) return;
    const TetMesh& m = s->mesh;
    const int64_t nv = m.vertex_count();
    Require(int64_t(m.positions.size()) == 3 * nv && m.tets.size() % 4 == 0 &&
                m.cell_regions.size() == m.tets.size() / 4,
            "mesh array sizes");
    for (int32_t v : m.tets) Require(v >= 0 && v < nv, "cell indices in range");
    for (int32_t v : s->vertex_map) Require(v >= -1 && v < nv, "vertex map in range");
    Require(pipeline::SerializeSimplifyResult(*s) == payload, "simplify payload round trip");
  } else {
    auto seg = pipeline::ParseSegmentResult(payload);
    if (!seg.ok()) return;
    const int64_t n = seg->labels.voxel_count();
    Require(n > 0 && int64_t(seg->labels.bytes.size()) == n &&
                int64_t(seg->interface_distance_voxels.size()) == n,
            "label and distance sizes match the dims");
    Require(pipeline::SerializeSegmentResult(*seg) == payload, "segment payload round trip");
  }
}

}  // namespace

int CheckpointEntry(const uint8_t* data, size_t size) {
  SetLastInputAccepted(false);
  if (size == 0) return 0;
  const bool simplify = data[0] & 1;
  const bool whole_file = data[0] & 2;
  const std::string rest(reinterpret_cast<const char*>(data) + 1, size - 1);
  if (!whole_file) {  // the payload parser alone (a fuzzer cannot forge the sha256)
    CheckPayload(simplify, rest);
    SetLastInputAccepted(simplify ? pipeline::ParseSimplifyResult(rest).ok()
                                  : pipeline::ParseSegmentResult(rest).ok());
    return 0;
  }
  // The file as ReadCheckpoint finds it on disk, under the key "k"; per process, so parallel
  // fuzzing jobs do not share it.
  const std::filesystem::path path =
      std::filesystem::temp_directory_path() /
      ("decima-checkpoint-fuzz-" + std::to_string(::getpid()) + ".ckpt");
  std::ofstream(path, std::ios::binary | std::ios::trunc) << rest;
  auto payload = pipeline::ReadCheckpoint(path, "k");
  std::filesystem::remove(path);
  if (!payload.ok()) return 0;
  CheckPayload(simplify, *payload);
  SetLastInputAccepted(true);
  return 0;
}

}  // namespace decima::fuzz
