// Closed triangle surfaces of the regions of a tetrahedral mesh, for the tools people take
// results to (3D printers and slicers read STL; web viewers read glTF).
//
// The surface of region r is the boundary of the union of the cells whose cell_regions entry is
// r: every cell face whose other side is a cell of another region or outside the mesh, oriented
// so that its normal points out of r. Such a boundary is closed by construction. Where two parts
// of a region touch only along an edge or at a vertex (diagonal voxels of a segmentation), the
// boundary is pinched there; the shared vertices are split, one copy per part, so that every edge
// of the output has exactly two triangles and every vertex one fan (a 2-manifold that 3D
// printing tools accept). Vertex positions are the mesh's own (LPS mm), so the surfaces agree
// with the tets; only the copies of a split vertex move, by a thousandth of their fan's size
// into their own part, because STL readers join vertices by position.
#pragma once

#include <array>
#include <cstdint>
#include <filesystem>
#include <string>
#include <vector>

#include "absl/status/status.h"
#include "core/mesh/tet_mesh.h"
#include "core/volume/regions.h"

namespace decima {

struct RegionSurface {
  uint8_t region = 0;              // the cell_regions value it bounds
  std::vector<float> positions;    // x, y, z per surface vertex, LPS mm
  std::vector<int32_t> triangles;  // 3 surface-vertex indices per face, normal out of the region

  int64_t vertex_count() const { return static_cast<int64_t>(positions.size() / 3); }
  int64_t triangle_count() const { return static_cast<int64_t>(triangles.size() / 3); }
};

// One surface per region that has cells, in increasing region order. `threads` as in
// BuildVertexTetAdjacency (the result does not depend on it). O(T * average vertex degree).
std::vector<RegionSurface> ExtractRegionSurfaces(const TetMesh& mesh, int threads = 1);

// Counts of a triangle surface's edges by how many triangles use them, and its Euler
// characteristic V - E + F (2 for a closed sphere-like surface).
struct SurfaceTopology {
  int64_t boundary_edges = 0;      // used by one triangle (a hole)
  int64_t non_manifold_edges = 0;  // used by three or more
  int64_t misoriented_edges = 0;   // two triangles that run the edge in the same direction
  int64_t euler_characteristic = 0;
};
SurfaceTopology MeasureTopology(const RegionSurface& surface);

// Binary STL (80-byte header holding `name`, little-endian float32, one facet normal per
// triangle). Writes to a temporary file beside `path` and renames it, so a failed write leaves no
// half file. Errors name the path.
absl::Status WriteStl(const RegionSurface& surface, const std::string& name,
                      const std::filesystem::path& path);

// A region's name and display colour (linear RGB in [0, 1]) for the formats that carry them.
struct RegionStyle {
  std::string name;
  float rgb[3] = {0.5f, 0.5f, 0.5f};
};
// A style from a region table's name and sRGB colour (core/volume/regions.h).
RegionStyle StyleOf(const std::string& name, const std::array<uint8_t, 3>& srgb);
// The style of region r without a table: name "region_<r>", colour kOkabeIto[r], the palette
// that stays distinct under the common colour-vision deficiencies.
RegionStyle DefaultRegionStyle(uint8_t region);

// Binary glTF 2.0 (.glb) holding every surface as its own named mesh and node with its colour,
// for web viewers and three.js. glTF's frame is +Y up, +Z toward the viewer, metres: a vertex at
// LPS (x, y, z) mm is written at (x, z, -y) / 1000, a rotation (facing is unchanged), so the
// head stands up and faces the viewer. `styles` has one entry per surface (or is empty: defaults).
// Written to a temporary file and renamed; errors name the path.
absl::Status WriteGlb(const std::vector<RegionSurface>& surfaces,
                      const std::vector<RegionStyle>& styles, const std::filesystem::path& path);

}  // namespace decima
