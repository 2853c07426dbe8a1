#include "core/mesh/region_surface.h"

#include <algorithm>
#include <array>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <fstream>
#include <numeric>
#include <system_error>
#include <tuple>

#include "absl/strings/str_cat.h"
#include "core/common/atomic_file.h"

namespace decima {
namespace {

// Writes `bytes` to `path` through a temporary file renamed over it (mesh_io's writers do the
// same), so a failed write leaves nothing behind.
absl::Status WriteFileAtomically(const std::filesystem::path& path, const std::string& bytes) {
  AtomicFile file;
  if (absl::Status s = file.Open(path); !s.ok()) return s;
  if (absl::Status s = file.Write(bytes); !s.ok()) return s;
  return file.Commit();
}

// A JSON string literal of `text` (quotes, backslashes and control characters escaped).
std::string JsonString(const std::string& text) {
  std::string out = "\"";
  for (unsigned char c : text) {
    if (c == '"' || c == '\\') {
      out += '\\';
      out += static_cast<char>(c);
    } else if (c < 0x20) {
      char buf[8];
      std::snprintf(buf, sizeof(buf), "\\u%04x", c);
      out += buf;
    } else {
      out += static_cast<char>(c);
    }
  }
  return out + "\"";
}

void AppendRaw(std::string* out, const void* data, size_t n) {
  out->append(static_cast<const char*>(data), n);
}

// A float as JSON with enough digits to read back the same float (glTF's accessor bounds must
// hold every value exactly).
std::string JsonNumber(float v) {
  char buf[32];
  std::snprintf(buf, sizeof(buf), "%.9g", v);
  return buf;
}

// Local vertices of face i of a tet (the face opposite vertex i), ordered so that the normal
// points out of a positively oriented tet.
constexpr int kFace[4][3] = {{1, 2, 3}, {0, 3, 2}, {0, 1, 3}, {0, 2, 1}};

// A face of the region surface: cell t's face opposite local vertex `opposite`.
struct SurfaceFace {
  int32_t tet;
  int8_t opposite;
  std::array<int32_t, 3> v;  // mesh vertices, outward order
};

// Local index of mesh vertex `v` in tet t, or -1.
int LocalIndex(const TetMesh& mesh, int64_t t, int32_t v) {
  for (int k = 0; k < 4; ++k) {
    if (mesh.tets[4 * t + k] == v) return k;
  }
  return -1;
}

std::array<int32_t, 3> FaceVertices(const TetMesh& mesh, int64_t t, int face) {
  return {mesh.tets[4 * t + kFace[face][0]], mesh.tets[4 * t + kFace[face][1]],
          mesh.tets[4 * t + kFace[face][2]]};
}

// The face of tet t other than `face` that holds the edge (a, b).
int OtherFaceWithEdge(const TetMesh& mesh, int64_t t, int face, int32_t a, int32_t b) {
  const int la = LocalIndex(mesh, t, a), lb = LocalIndex(mesh, t, b);
  for (int m = 0; m < 4; ++m) {
    if (m != la && m != lb && m != face) return m;
  }
  return -1;
}

struct UnionFind {
  std::vector<int32_t> parent;
  explicit UnionFind(size_t n) : parent(n) { std::iota(parent.begin(), parent.end(), 0); }
  int32_t Find(int32_t x) {
    while (parent[x] != x) {
      parent[x] = parent[parent[x]];
      x = parent[x];
    }
    return x;
  }
  // The smaller root wins, so the classes do not depend on the order of the unions.
  void Union(int32_t a, int32_t b) {
    a = Find(a);
    b = Find(b);
    if (a != b) parent[std::max(a, b)] = std::min(a, b);
  }
};

// STL and the readers of most surface formats join vertices by position, which would join the
// copies of a split vertex again. Each copy therefore moves a thousandth of the way toward the
// centroid of its own fan (the triangles around it): the parts separate by microns, each into
// its own side, and the surface still agrees with the tets to far below a voxel.
void SeparateSplitCopies(const std::vector<int32_t>& mesh_vertex, RegionSurface* s) {
  std::vector<int32_t> copies_of(
      mesh_vertex.empty() ? 0 : *std::max_element(mesh_vertex.begin(), mesh_vertex.end()) + 1, 0);
  for (int32_t v : mesh_vertex) ++copies_of[v];
  std::vector<double> sum(3 * mesh_vertex.size(), 0.0);
  std::vector<int32_t> count(mesh_vertex.size(), 0);
  for (int64_t f = 0; f < s->triangle_count(); ++f) {
    for (int k = 0; k < 3; ++k) {
      const int32_t v = s->triangles[3 * f + k];
      if (copies_of[mesh_vertex[v]] < 2) continue;
      for (int j = 1; j < 3; ++j) {
        const int32_t w = s->triangles[3 * f + (k + j) % 3];
        for (int c = 0; c < 3; ++c) sum[3 * v + c] += s->positions[3 * w + c];
      }
      count[v] += 2;
    }
  }
  for (size_t v = 0; v < mesh_vertex.size(); ++v) {
    if (count[v] == 0) continue;
    for (int c = 0; c < 3; ++c) {
      const double centroid = sum[3 * v + c] / count[v];
      s->positions[3 * v + c] += static_cast<float>(1e-3 * (centroid - s->positions[3 * v + c]));
    }
  }
}

// Builds the surface of one region from its faces (sorted by tet, then face).
RegionSurface BuildSurface(const TetMesh& mesh, const VertexTetAdjacency& adj, uint8_t region,
                           const std::vector<SurfaceFace>& faces) {
  const auto key = [](int64_t t, int face) { return 4 * t + face; };
  std::vector<int64_t> keys(faces.size());
  for (size_t f = 0; f < faces.size(); ++f) keys[f] = key(faces[f].tet, faces[f].opposite);
  const auto face_index = [&](int64_t t, int face) -> int64_t {
    auto it = std::lower_bound(keys.begin(), keys.end(), key(t, face));
    return (it != keys.end() && *it == key(t, face)) ? it - keys.begin() : -1;
  };

  // partner[3f + e]: the face on the other side of face f's edge e (from corner e to e + 1) in
  // the same part of the region: the walk around the edge through the region's cells, from f to
  // the first face that leaves the region ("solid" pairing).
  std::vector<int64_t> partner(3 * faces.size(), -1);
  for (size_t f = 0; f < faces.size(); ++f) {
    for (int e = 0; e < 3; ++e) {
      const int32_t a = faces[f].v[e], b = faces[f].v[(e + 1) % 3];
      int64_t t = faces[f].tet;
      int face = faces[f].opposite;
      for (int step = 0; step < 1024; ++step) {
        const int next = OtherFaceWithEdge(mesh, t, face, a, b);
        const auto nv = FaceVertices(mesh, t, next);
        const int64_t across = TetAcrossFace(mesh, adj, t, nv[0], nv[1], nv[2]);
        if (across < 0 || mesh.cell_regions[across] != region) {
          partner[3 * f + e] = face_index(t, next);
          break;
        }
        // Enter the neighbour through the shared face: the face opposite its vertex not on it.
        int entered = -1;
        for (int k = 0; k < 4; ++k) {
          const int32_t w = mesh.tets[4 * across + k];
          if (w != nv[0] && w != nv[1] && w != nv[2]) entered = k;
        }
        t = across;
        face = entered;
      }
    }
  }

  // Surface vertices: the classes of corners joined across every paired edge.
  std::vector<int32_t> mesh_vertex;    // per surface vertex
  std::vector<int32_t> corner_vertex;  // per corner, its surface vertex
  const auto split = [&] {
    UnionFind corners(3 * faces.size());
    for (size_t f = 0; f < faces.size(); ++f) {
      for (int e = 0; e < 3; ++e) {
        const int64_t g = partner[3 * f + e];
        if (g < 0) continue;  // not reachable on a conforming mesh; leaves the corner alone
        const int32_t a = faces[f].v[e], b = faces[f].v[(e + 1) % 3];
        for (int k = 0; k < 3; ++k) {
          const int32_t w = faces[g].v[k];
          const int32_t c = static_cast<int32_t>(w == a ? 3 * f + e : 3 * f + (e + 1) % 3);
          if (w == a || w == b) corners.Union(c, static_cast<int32_t>(3 * g + k));
        }
      }
    }
    mesh_vertex.clear();
    corner_vertex.assign(3 * faces.size(), -1);
    std::vector<int32_t> vertex_of_root(3 * faces.size(), -1);
    for (size_t c = 0; c < 3 * faces.size(); ++c) {
      const int32_t root = corners.Find(static_cast<int32_t>(c));
      if (vertex_of_root[root] < 0) {
        vertex_of_root[root] = static_cast<int32_t>(mesh_vertex.size());
        mesh_vertex.push_back(faces[c / 3].v[c % 3]);
      }
      corner_vertex[c] = vertex_of_root[root];
    }
  };
  split();

  // Where a region wraps around one of its own edges (a "C" whose two ends touch along it), the
  // solid pairing leaves one fan at each end that runs through the edge twice: four triangles on
  // one pair of surface vertices. Pairing across the empty side instead opens the C there: each
  // end's fan falls into two, the vertices split, and the edge becomes two. Edges with more than
  // two wedges keep the solid pairing.
  for (int round = 0; round < 4; ++round) {
    std::vector<std::tuple<int32_t, int32_t, int64_t>> edges;  // (low, high, 3f + e)
    for (size_t f = 0; f < faces.size(); ++f) {
      for (int e = 0; e < 3; ++e) {
        const int32_t u = corner_vertex[3 * f + e], v = corner_vertex[3 * f + (e + 1) % 3];
        edges.emplace_back(std::min(u, v), std::max(u, v), static_cast<int64_t>(3 * f + e));
      }
    }
    std::sort(edges.begin(), edges.end());
    bool changed = false;
    for (size_t i = 0; i < edges.size();) {
      size_t j = i;
      while (j < edges.size() && std::get<0>(edges[j]) == std::get<0>(edges[i]) &&
             std::get<1>(edges[j]) == std::get<1>(edges[i])) {
        ++j;
      }
      if (j - i == 4) {
        // Two faces run the edge one way (f1, f3), two the other (their solid partners).
        std::vector<int64_t> forward, backward;
        const int32_t a = faces[std::get<2>(edges[i]) / 3].v[std::get<2>(edges[i]) % 3];
        for (size_t k = i; k < j; ++k) {
          const int64_t fe = std::get<2>(edges[k]);
          (faces[fe / 3].v[fe % 3] == a ? forward : backward).push_back(fe);
        }
        if (forward.size() == 2 && backward.size() == 2) {
          const int64_t f1 = forward[0], f3 = forward[1];
          const int64_t g1 = partner[f1], g3 = partner[f3];
          // Find each backward edge's index by its face, then swap the partners.
          const auto edge_of = [&](int64_t face) {
            return backward[0] / 3 == face ? backward[0] : backward[1];
          };
          if (g1 >= 0 && g3 >= 0 && g1 != g3) {
            partner[f1] = g3;
            partner[f3] = g1;
            partner[edge_of(g3)] = f1 / 3;
            partner[edge_of(g1)] = f3 / 3;
            changed = true;
          }
        }
      }
      i = j;
    }
    if (!changed) break;
    split();
  }

  RegionSurface out;
  out.region = region;
  out.triangles = corner_vertex;
  out.positions.resize(3 * mesh_vertex.size());
  for (size_t v = 0; v < mesh_vertex.size(); ++v) {
    for (int k = 0; k < 3; ++k) out.positions[3 * v + k] = mesh.positions[3 * mesh_vertex[v] + k];
  }
  SeparateSplitCopies(mesh_vertex, &out);
  return out;
}

}  // namespace

std::vector<RegionSurface> ExtractRegionSurfaces(const TetMesh& mesh, int threads) {
  const VertexTetAdjacency adj = BuildVertexTetAdjacency(mesh, threads);
  std::array<std::vector<SurfaceFace>, 256> by_region;
  for (int64_t t = 0; t < mesh.tet_count(); ++t) {
    const uint8_t r = mesh.cell_regions[t];
    for (int face = 0; face < 4; ++face) {
      const auto v = FaceVertices(mesh, t, face);
      const int64_t across = TetAcrossFace(mesh, adj, t, v[0], v[1], v[2]);
      if (across >= 0 && mesh.cell_regions[across] == r) continue;
      by_region[r].push_back({static_cast<int32_t>(t), static_cast<int8_t>(face), v});
    }
  }
  std::vector<RegionSurface> out;
  for (int r = 0; r < 256; ++r) {
    if (by_region[r].empty()) continue;
    out.push_back(BuildSurface(mesh, adj, static_cast<uint8_t>(r), by_region[r]));
  }
  return out;
}

SurfaceTopology MeasureTopology(const RegionSurface& s) {
  // (low, high, +1 when the triangle runs low -> high) per triangle edge, sorted by edge.
  std::vector<std::tuple<int32_t, int32_t, int>> edges;
  edges.reserve(s.triangles.size());
  for (int64_t f = 0; f < s.triangle_count(); ++f) {
    for (int e = 0; e < 3; ++e) {
      const int32_t a = s.triangles[3 * f + e], b = s.triangles[3 * f + (e + 1) % 3];
      edges.emplace_back(std::min(a, b), std::max(a, b), a < b ? 1 : -1);
    }
  }
  std::sort(edges.begin(), edges.end());
  SurfaceTopology topo;
  int64_t edge_count = 0;
  for (size_t i = 0; i < edges.size();) {
    size_t j = i;
    int direction_sum = 0;
    while (j < edges.size() && std::get<0>(edges[j]) == std::get<0>(edges[i]) &&
           std::get<1>(edges[j]) == std::get<1>(edges[i])) {
      direction_sum += std::get<2>(edges[j]);
      ++j;
    }
    const size_t uses = j - i;
    ++edge_count;
    if (uses == 1) ++topo.boundary_edges;
    if (uses > 2) ++topo.non_manifold_edges;
    if (uses == 2 && direction_sum != 0) ++topo.misoriented_edges;
    i = j;
  }
  topo.euler_characteristic = s.vertex_count() - edge_count + s.triangle_count();
  return topo;
}

absl::Status WriteStl(const RegionSurface& s, const std::string& name,
                      const std::filesystem::path& path) {
  if (s.triangle_count() > UINT32_MAX) {
    return absl::InvalidArgumentError(
        absl::StrCat(path.string(), ": ", s.triangle_count(), " triangles do not fit in STL"));
  }
  std::string out;
  out.reserve(84 + 50 * static_cast<size_t>(s.triangle_count()));
  // The header must not start with "solid": readers take such a file for ASCII STL.
  char header[80] = {};
  const std::string text = absl::StrCat("decima region surface: ", name);
  std::memcpy(header, text.data(), std::min<size_t>(text.size(), sizeof(header)));
  AppendRaw(&out, header, sizeof(header));
  const uint32_t count = static_cast<uint32_t>(s.triangle_count());
  AppendRaw(&out, &count, 4);  // x86 and ARM are little-endian, as STL is
  for (int64_t f = 0; f < s.triangle_count(); ++f) {
    float p[3][3];
    for (int k = 0; k < 3; ++k) {
      for (int c = 0; c < 3; ++c) p[k][c] = s.positions[3 * s.triangles[3 * f + k] + c];
    }
    const Eigen::Vector3f a(p[0][0], p[0][1], p[0][2]), b(p[1][0], p[1][1], p[1][2]),
        c(p[2][0], p[2][1], p[2][2]);
    const Eigen::Vector3f n = (b - a).cross(c - a).normalized();
    const float normal[3] = {n.x(), n.y(), n.z()};
    AppendRaw(&out, normal, sizeof(normal));
    AppendRaw(&out, p, sizeof(p));
    const uint16_t attribute = 0;
    AppendRaw(&out, &attribute, sizeof(attribute));
  }
  return WriteFileAtomically(path, out);
}

}  // namespace decima

namespace decima {

RegionStyle StyleOf(const std::string& name, const std::array<uint8_t, 3>& srgb) {
  RegionStyle s;
  s.name = name;
  for (int c = 0; c < 3; ++c) {
    // glTF's baseColorFactor is linear; convert from sRGB.
    const float v = srgb[c] / 255.0f;
    s.rgb[c] = v <= 0.04045f ? v / 12.92f : std::pow((v + 0.055f) / 1.055f, 2.4f);
  }
  return s;
}

RegionStyle DefaultRegionStyle(uint8_t region) {
  return StyleOf(absl::StrCat("region_", int{region}), kOkabeIto[region % kOkabeIto.size()]);
}

absl::Status WriteGlb(const std::vector<RegionSurface>& surfaces,
                      const std::vector<RegionStyle>& styles, const std::filesystem::path& path) {
  if (!styles.empty() && styles.size() != surfaces.size()) {
    return absl::InvalidArgumentError(absl::StrCat(
        path.string(), ": ", styles.size(), " region styles for ", surfaces.size(), " surfaces"));
  }
  std::string bin;
  std::string nodes, meshes, materials, accessors, views;
  for (size_t i = 0; i < surfaces.size(); ++i) {
    const RegionSurface& s = surfaces[i];
    const RegionStyle style = styles.empty() ? DefaultRegionStyle(s.region) : styles[i];
    float lo[3] = {INFINITY, INFINITY, INFINITY}, hi[3] = {-INFINITY, -INFINITY, -INFINITY};
    if (s.vertex_count() == 0) lo[0] = lo[1] = lo[2] = hi[0] = hi[1] = hi[2] = 0;
    const size_t positions_at = bin.size();
    for (int64_t v = 0; v < s.vertex_count(); ++v) {
      const float p[3] = {s.positions[3 * v] / 1000.0f, s.positions[3 * v + 2] / 1000.0f,
                          -s.positions[3 * v + 1] / 1000.0f};
      for (int c = 0; c < 3; ++c) {
        lo[c] = std::min(lo[c], p[c]);
        hi[c] = std::max(hi[c], p[c]);
      }
      AppendRaw(&bin, p, sizeof(p));  // x86 and ARM are little-endian, as glTF is
    }
    const size_t indices_at = bin.size();
    AppendRaw(&bin, s.triangles.data(), s.triangles.size() * sizeof(int32_t));
    const size_t a = 2 * i;  // this surface's accessors and buffer views: a (positions), a + 1
    const char* sep = i == 0 ? "" : ",";
    absl::StrAppend(&views, sep, "{\"buffer\":0,\"byteOffset\":", positions_at,
                    ",\"byteLength\":", indices_at - positions_at, ",\"target\":34962},",
                    "{\"buffer\":0,\"byteOffset\":", indices_at,
                    ",\"byteLength\":", bin.size() - indices_at, ",\"target\":34963}");
    absl::StrAppend(&accessors, sep, "{\"bufferView\":", a,
                    ",\"componentType\":5126,\"type\":\"VEC3\",\"count\":", s.vertex_count(),
                    ",\"min\":[", JsonNumber(lo[0]), ",", JsonNumber(lo[1]), ",", JsonNumber(lo[2]),
                    "],\"max\":[", JsonNumber(hi[0]), ",", JsonNumber(hi[1]), ",",
                    JsonNumber(hi[2]), "]},", "{\"bufferView\":", a + 1,
                    ",\"componentType\":5125,\"type\":\"SCALAR\",\"count\":", s.triangles.size(),
                    "}");
    absl::StrAppend(&materials, sep, "{\"name\":", JsonString(style.name),
                    ",\"pbrMetallicRoughness\":{\"baseColorFactor\":[", JsonNumber(style.rgb[0]),
                    ",", JsonNumber(style.rgb[1]), ",", JsonNumber(style.rgb[2]),
                    ",1],\"metallicFactor\":0,", "\"roughnessFactor\":0.8}}");
    absl::StrAppend(&meshes, sep, "{\"name\":", JsonString(style.name),
                    ",\"primitives\":[{\"attributes\":{\"POSITION\":", a, "},\"indices\":", a + 1,
                    ",\"material\":", i, ",\"mode\":4}]}");
    absl::StrAppend(&nodes, sep, "{\"name\":", JsonString(style.name), ",\"mesh\":", i, "}");
  }
  std::string scene_nodes;
  for (size_t i = 0; i < surfaces.size(); ++i) absl::StrAppend(&scene_nodes, i ? "," : "", i);
  std::string json = absl::StrCat(
      "{\"asset\":{\"version\":\"2.0\",\"generator\":\"decima\"},\"scene\":0,",
      "\"scenes\":[{\"nodes\":[", scene_nodes, "]}],\"nodes\":[", nodes, "],\"meshes\":[", meshes,
      "],\"materials\":[", materials, "],\"accessors\":[", accessors, "],\"bufferViews\":[", views,
      "],\"buffers\":[{\"byteLength\":", bin.size(), "}]}");
  while (json.size() % 4 != 0) json += ' ';
  while (bin.size() % 4 != 0) bin += '\0';
  const uint64_t total = 12 + 8 + json.size() + 8 + bin.size();
  if (total > UINT32_MAX) {
    return absl::InvalidArgumentError(
        absl::StrCat(path.string(), ": ", total, " bytes do not fit in one .glb (4 GiB)"));
  }
  std::string out;
  out.reserve(total);
  const uint32_t header[3] = {0x46546C67u, 2u, static_cast<uint32_t>(total)};  // "glTF", v2
  AppendRaw(&out, header, sizeof(header));
  const uint32_t json_chunk[2] = {static_cast<uint32_t>(json.size()), 0x4E4F534Au};  // "JSON"
  AppendRaw(&out, json_chunk, sizeof(json_chunk));
  out += json;
  const uint32_t bin_chunk[2] = {static_cast<uint32_t>(bin.size()), 0x004E4942u};  // "BIN\0"
  AppendRaw(&out, bin_chunk, sizeof(bin_chunk));
  out += bin;
  return WriteFileAtomically(path, out);
}

}  // namespace decima
