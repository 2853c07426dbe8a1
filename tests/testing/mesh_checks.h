// Mesh property checks shared by the mesh and simplify tests.
#pragma once

#include <algorithm>
#include <array>
#include <cstdint>
#include <map>

#include "core/mesh/tet_mesh.h"

namespace decima::testing {

// Number of cells using each face (sorted vertex triple): 2 inside a conforming mesh, 1 on its
// boundary, never more.
inline std::map<std::array<int32_t, 3>, int> FaceUse(const TetMesh& m) {
  std::map<std::array<int32_t, 3>, int> use;
  for (int64_t t = 0; t < m.tet_count(); ++t) {
    const int32_t* v = &m.tets[4 * t];
    for (int skip = 0; skip < 4; ++skip) {
      std::array<int32_t, 3> f;
      int n = 0;
      for (int q = 0; q < 4; ++q) {
        if (q != skip) f[n++] = v[q];
      }
      std::sort(f.begin(), f.end());
      ++use[f];
    }
  }
  return use;
}

}  // namespace decima::testing
