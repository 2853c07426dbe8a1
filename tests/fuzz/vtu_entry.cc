#include <unistd.h>

#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <string>

#include "core/mesh/mesh_io.h"
#include "tests/fuzz/fuzz_entries.h"
#include "tests/fuzz/fuzz_require.h"

namespace decima::fuzz {

int ReadVtuEntry(const uint8_t* data, size_t size) {
  // ReadVtu reads files (it preads the appended block), so the input becomes one; per process,
  // so parallel fuzzing jobs do not share it.
  const std::filesystem::path path = std::filesystem::temp_directory_path() /
                                     ("decima-vtu-fuzz-" + std::to_string(::getpid()) + ".vtu");
  if (std::FILE* f = std::fopen(path.c_str(), "wb")) {
    if (size > 0) std::fwrite(data, 1, size, f);
    std::fclose(f);
  }
  VtuReadReport report;
  auto mesh = ReadVtu(path, &report);
  std::filesystem::remove(path);
  if (!mesh.ok()) return 0;
  const TetMesh& m = *mesh;
  const int64_t nv = m.vertex_count(), nt = m.tet_count();
  Require(int64_t(m.positions.size()) == 3 * nv && int64_t(m.labels.size()) == nv &&
              int64_t(m.interface_distance.size()) == nv && int64_t(m.vertex_flags.size()) == nv &&
              m.tets.size() % 4 == 0 && int64_t(m.cell_regions.size()) == nt,
          "array sizes");
  Require(!report.scalar_array.empty(), "the field has a source array");
  for (int64_t v = 0; v < nv; ++v)
    Require(std::isfinite(m.scalars[v]) && m.labels[v] < 8, "finite scalars, labels < 8");
  for (int32_t i : m.tets) Require(i >= 0 && i < nv, "indices in range");
  for (int64_t t = 0; t < nt; ++t) {
    Require(TetVolume(m, t) > 0, "positive volumes");
    Require(m.cell_regions[t] < 8, "regions < 8");
  }
  return 0;
}

}  // namespace decima::fuzz
