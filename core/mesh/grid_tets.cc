#include "core/mesh/grid_tets.h"

#include <algorithm>
#include <array>
#include <cstdlib>
#include <utility>

namespace decima {
namespace {

// Cube corner c sits at offset (c & 1, (c >> 1) & 1, (c >> 2) & 1).
using TetTemplate = std::array<std::array<int, 4>, 5>;

// Even cubes ((i + j + k) % 2 == 0) keep the corners with an even number of set bits as the
// ones cut off; odd cubes the opposite, so each face diagonal agrees with the neighbour's.
constexpr TetTemplate kEvenCube = {
    {{1, 2, 4, 7}, {0, 1, 2, 4}, {3, 2, 1, 7}, {5, 1, 4, 7}, {6, 2, 4, 7}}};
constexpr TetTemplate kOddCube = {
    {{0, 3, 5, 6}, {1, 0, 3, 5}, {2, 0, 3, 6}, {4, 0, 5, 6}, {7, 3, 5, 6}}};

int CornerAxis(int c, int axis) { return (c >> axis) & 1; }

// Signed volume (times 6) of a template tet in index space.
int IndexVolume(const std::array<int, 4>& tet) {
  int e[3][3];
  for (int r = 0; r < 3; ++r) {
    for (int a = 0; a < 3; ++a) e[r][a] = CornerAxis(tet[r + 1], a) - CornerAxis(tet[0], a);
  }
  return e[0][0] * (e[1][1] * e[2][2] - e[1][2] * e[2][1]) -
         e[0][1] * (e[1][0] * e[2][2] - e[1][2] * e[2][0]) +
         e[0][2] * (e[1][0] * e[2][1] - e[1][1] * e[2][0]);
}

}  // namespace

GridTets::GridTets(int64_t nx, int64_t ny, int64_t nz, bool flip)
    : nx_(nx), ny_(ny), nz_(nz), flip_(flip) {
  cube_stride_[0] = 1;
  cube_stride_[1] = nx - 1;
  cube_stride_[2] = (nx - 1) * (ny - 1);
  vertex_stride_[0] = 1;
  vertex_stride_[1] = static_cast<int32_t>(nx);
  vertex_stride_[2] = static_cast<int32_t>(nx * ny);
  last_[0] = static_cast<int32_t>(nx - 2);
  last_[1] = static_cast<int32_t>(ny - 2);
  last_[2] = static_cast<int32_t>(nz - 2);
  TetTemplate corners[2];  // per parity, in the stored vertex order (after the flip)
  for (int parity = 0; parity < 2; ++parity) {
    TetTemplate t = parity ? kOddCube : kEvenCube;
    for (int s = 0; s < 5; ++s) {
      // Positively oriented in index space, then all reversed if the map to mm reverses it.
      if ((IndexVolume(t[s]) < 0) != flip) std::swap(t[s][2], t[s][3]);
      corners[parity][s] = t[s];
      for (int q = 0; q < 4; ++q) {
        const int c = t[s][q];
        offsets_[parity][s][q] = static_cast<int32_t>(
            CornerAxis(c, 0) + nx * (CornerAxis(c, 1) + ny * CornerAxis(c, 2)));
      }
    }
  }
  // Face adjacency from the templates: a face whose three corners share a coordinate lies on
  // that side of the cube and is a face of the next cube (the other parity, its corners mirrored
  // along the axis); any other face is shared with another tet of the same cube. The mesh is
  // conforming, so exactly one tet matches; the table is checked against the materialized mesh's
  // adjacency in tetrahedralize_test.
  auto holds = [](const std::array<int, 4>& tet, const int face[3]) {
    for (int k = 0; k < 3; ++k) {
      if (std::find(tet.begin(), tet.end(), face[k]) == tet.end()) return false;
    }
    return true;
  };
  for (int parity = 0; parity < 2; ++parity) {
    for (int s = 0; s < 5; ++s) {
      for (int q = 0; q < 4; ++q) {
        int face[3], n = 0;
        for (int r = 0; r < 4; ++r)
          if (r != q) face[n++] = corners[parity][s][r];
        Across& a = across_[parity][s][q];
        for (int axis = 0; axis < 3 && a.axis < 0; ++axis) {
          const int side = CornerAxis(face[0], axis);
          if (CornerAxis(face[1], axis) != side || CornerAxis(face[2], axis) != side) continue;
          a.axis = static_cast<int8_t>(axis);
          a.dir = static_cast<int8_t>(side ? 1 : -1);
          for (int& c : face) c ^= 1 << axis;
        }
        const int other = a.axis < 0 ? parity : 1 - parity;
        int found = -1;
        for (int s2 = 0; s2 < 5; ++s2) {
          if ((a.axis >= 0 || s2 != s) && holds(corners[other][s2], face)) found = s2;
        }
        if (found < 0) std::abort();  // the templates are not conforming: a bug, not input
        a.s = static_cast<int8_t>(found);
      }
    }
  }
}

}  // namespace decima
