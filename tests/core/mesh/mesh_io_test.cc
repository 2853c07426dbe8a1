#include "core/mesh/mesh_io.h"

#include <sys/wait.h>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <fstream>
#include <limits>
#include <map>
#include <set>
#include <sstream>
#include <string>
#include <vector>

#include <gtest/gtest.h>

#include "core/mesh/region_surface.h"
#include "core/mesh/tetrahedralize.h"
#include "core/volume/phantom.h"
#include "tests/testing/test_data.h"

namespace decima {
namespace {

namespace fs = std::filesystem;
constexpr float kInf = std::numeric_limits<float>::infinity();

// Two positively oriented tets sharing the face (1, 2, 3), in regions 0 and 2.
TetMesh TwoTets() {
  TetMesh m;
  m.positions = {0, 0, 0, 1, 0, 0, 0, 1, 0, 0, 0, 1, 1, 1, 1};
  m.scalars = {10.5f, -2.0f, 3.25f, 1e6f, 0.0f};
  m.labels = {0, 0, 2, 2, 1};
  m.interface_distance = {0.0f, 0.25f, 1.5f, kInf, 7.0f};
  m.vertex_flags = {kFeatureVertex, kFeatureVertex | kExteriorBoundaryVertex,
                    kExteriorBoundaryVertex, 0, kExteriorBoundaryVertex};
  m.tets = {0, 1, 2, 3, 1, 2, 3, 4};
  m.cell_regions = {0, 2};
  return m;
}

// A noisy 3-region head phantom, tetrahedralized with its labels and a crude interface distance
// (0.5 voxel next to a different label, 3 elsewhere) so that feature flags are set.
TetMesh PhantomMesh(std::array<int64_t, 3> dims = {20, 18, 14}) {
  HeadPhantomOptions o;
  o.dims = dims;
  o.spacing = {1.0, 1.2, 2.0};
  o.region_means = {0.0, 1000.0, 400.0};
  o.noise_sigma = 60.0;
  auto p = MakeHeadPhantom(o);
  EXPECT_TRUE(p.ok()) << p.status();
  const Volume& lab = p->labels;
  std::vector<float> dist(lab.voxel_count(), 3.0f);
  const uint8_t* l = lab.data<uint8_t>();
  for (int64_t k = 0; k < dims[2]; ++k)
    for (int64_t j = 0; j < dims[1]; ++j)
      for (int64_t i = 0; i < dims[0]; ++i) {
        const int64_t v = lab.Index(i, j, k);
        if ((i + 1 < dims[0] && l[lab.Index(i + 1, j, k)] != l[v]) ||
            (i > 0 && l[lab.Index(i - 1, j, k)] != l[v]) ||
            (j + 1 < dims[1] && l[lab.Index(i, j + 1, k)] != l[v]) ||
            (j > 0 && l[lab.Index(i, j - 1, k)] != l[v]) ||
            (k + 1 < dims[2] && l[lab.Index(i, j, k + 1)] != l[v]) ||
            (k > 0 && l[lab.Index(i, j, k - 1)] != l[v]))
          dist[v] = 0.5f;
      }
  TetrahedralizeOptions t;
  t.labels = &lab;
  t.interface_distance = dist.data();
  auto m = Tetrahedralize(p->image, t);
  EXPECT_TRUE(m.ok()) << m.status();
  return *std::move(m);
}

void ExpectSameMesh(const TetMesh& a, const TetMesh& b) {
  EXPECT_EQ(a.positions, b.positions);
  EXPECT_EQ(a.scalars, b.scalars);
  EXPECT_EQ(a.labels, b.labels);
  EXPECT_EQ(a.interface_distance, b.interface_distance);
  EXPECT_EQ(a.vertex_flags, b.vertex_flags);
  EXPECT_EQ(a.tets, b.tets);
  EXPECT_EQ(a.cell_regions, b.cell_regions);
}

std::string ReadAll(const fs::path& p) {
  std::ifstream in(p, std::ios::binary);
  std::stringstream ss;
  ss << in.rdbuf();
  return ss.str();
}

void WriteAll(const fs::path& p, const std::string& bytes) {
  std::ofstream out(p, std::ios::binary | std::ios::trunc);
  out.write(bytes.data(), static_cast<std::streamsize>(bytes.size()));
}

// Runs a shell command; returns its exit code and stdout.
std::pair<int, std::string> RunCommand(const std::string& cmd) {
  std::string out;
  FILE* f = popen((cmd + " 2>&1").c_str(), "r");
  if (f == nullptr) return {-1, ""};
  char buf[4096];
  size_t n;
  while ((n = fread(buf, 1, sizeof(buf), f)) > 0) out.append(buf, n);
  const int status = pclose(f);
  return {WIFEXITED(status) ? WEXITSTATUS(status) : -1, out};
}

std::string Quote(const fs::path& p) { return "'" + p.string() + "'"; }

// "key value..." lines -> key -> rest of the line. Repeated keys get " #n" suffixes.
std::map<std::string, std::string> ParseFacts(const std::string& text) {
  std::map<std::string, std::string> facts;
  std::istringstream in(text);
  std::string line;
  while (std::getline(in, line)) {
    const size_t sp = line.find(' ');
    if (sp == std::string::npos) continue;
    std::string key = line.substr(0, sp), value = line.substr(sp + 1);
    // "physical 3 120" -> key "physical 3", value "120" (also elementary/name/array lines).
    if (key == "name") {  // "name <dim> <tag> <name>" -> "name <tag>" = "<dim> <name>"
      std::istringstream fields(value);
      std::string dim, tag, name;
      fields >> dim >> tag;
      std::getline(fields >> std::ws, name);  // names may hold spaces
      key += " " + tag;
      value = dim + " " + name;
    } else if (key == "physical" || key == "elementary" || key == "point_array" ||
               key == "cell_array") {
      const size_t sp2 = value.find(' ');
      key += " " + value.substr(0, sp2);
      value = value.substr(sp2 + 1);
    }
    facts[key] = value;
  }
  return facts;
}

// The Python with VTK (Debian's python3-vtk9 lives in /usr/bin/python3, which a pyenv or venv
// python3 earlier on PATH may hide), or "" if none. $DECIMA_PYTHON overrides.
std::string PythonWithVtk() {
  std::vector<std::string> candidates;
  if (const char* env = std::getenv("DECIMA_PYTHON")) candidates.push_back(env);
  candidates.push_back("/usr/bin/python3");
  candidates.push_back("python3");
  for (const std::string& py : candidates)
    if (RunCommand(py + " -c 'import vtk' >/dev/null").first == 0) return py;
  return "";
}

std::string GmshBinary() {
  auto [rc, out] = RunCommand("command -v gmsh");
  if (rc != 0) return "";
  while (!out.empty() && (out.back() == '\n' || out.back() == ' ')) out.pop_back();
  return out;
}

// Any Python 3 for check_gmsh.py (it needs only the standard library), or "".
std::string AnyPython() {
  for (const char* py : {"/usr/bin/python3", "python3"})
    if (RunCommand(std::string(py) + " -c 'pass' >/dev/null").first == 0) return py;
  return "";
}

double AbsSum(const std::vector<float>& v) {
  double s = 0;
  for (float x : v) s += std::abs(x);
  return s;
}
// Sum over tets of |coordinates| of their 4 vertices: checks connectivity without node numbers.
double TetCoordAbsSum(const TetMesh& m) {
  double s = 0;
  for (int32_t v : m.tets)
    for (int c = 0; c < 3; ++c) s += std::abs(m.positions[3 * v + c]);
  return s;
}
double TotalVolume(const TetMesh& m) {
  double s = 0;
  for (int64_t t = 0; t < m.tet_count(); ++t) s += TetVolume(m, t);
  return s;
}
double Sum(const std::vector<float>& v) {
  double s = 0;
  for (float x : v)
    if (std::isfinite(x)) s += x;
  return s;
}
template <typename T>
double SumInt(const std::vector<T>& v) {
  double s = 0;
  for (T x : v) s += x;
  return s;
}

fs::path Script(const char* name) { return fs::path(DECIMA_MESH_TEST_DIR) / name; }

// ---------------------------------------------------------------------------------------------
// Round trips

// Every encoding WriteVtu offers: raw, zlib (the default), LZMA, by file name.
struct VtuEncoding {
  const char* file;
  VtuWriteOptions options;
};
const VtuEncoding kVtuEncodings[] = {
    {"raw.vtu", {.compress = false}},
    {"zlib.vtu", {.compress = true, .compressor = VtuCompressor::kZlib}},
    {"lzma.vtu", {.compress = true, .compressor = VtuCompressor::kLzma}},
};

TEST(MeshIo, VtuRoundTripOfTinyMeshIsExactRawAndCompressed) {
  const TetMesh m = TwoTets();
  const fs::path dir = testing::MakeScratchDir("vtu_tiny");
  for (const VtuEncoding& e : kVtuEncodings) {
    const fs::path p = dir / e.file;
    ASSERT_TRUE(WriteVtu(m, p, e.options).ok());
    auto back = ReadVtu(p);
    ASSERT_TRUE(back.ok()) << back.status();
    ExpectSameMesh(m, *back);
  }
}

TEST(MeshIo, EmptyMeshRoundTripsAndWritesEveryFormat) {
  const TetMesh empty;
  const fs::path dir = testing::MakeScratchDir("empty");
  for (const VtuEncoding& e : kVtuEncodings) {
    const fs::path p = dir / e.file;
    ASSERT_TRUE(WriteVtu(empty, p, e.options).ok());
    auto back = ReadVtu(p);
    ASSERT_TRUE(back.ok()) << back.status();
    ExpectSameMesh(empty, *back);
  }
  EXPECT_TRUE(WriteGmsh(empty, dir / "e.msh").ok());
  EXPECT_TRUE(WriteMedit(empty, dir / "e.mesh").ok());
}

TEST(MeshIo, VtuRoundTripOfPhantomMeshIsExact) {
  const TetMesh m = PhantomMesh();
  const fs::path dir = testing::MakeScratchDir("vtu_phantom");
  for (VtuEncoding e : kVtuEncodings) {
    const fs::path p = dir / e.file;
    e.options.level = 6;
    e.options.threads = 2;
    ASSERT_TRUE(WriteVtu(m, p, e.options).ok());
    auto back = ReadVtu(p);
    ASSERT_TRUE(back.ok()) << back.status();
    ExpectSameMesh(m, *back);
  }
  // Noise compresses poorly, but positions, connectivity and labels compress well; LZMA with
  // the delta-coded offsets better than zlib.
  EXPECT_LT(fs::file_size(dir / "zlib.vtu"), fs::file_size(dir / "raw.vtu") * 3 / 4);
  EXPECT_LT(fs::file_size(dir / "lzma.vtu"), fs::file_size(dir / "zlib.vtu"));
}

TEST(MeshIo, VtuRawFileHoldsExactlyTheArraysAndTheirHeaders) {
  const TetMesh m = TwoTets();
  const fs::path p = testing::MakeScratchDir("vtu_size") / "m.vtu";
  ASSERT_TRUE(WriteVtu(m, p, {.compress = false}).ok());
  const std::string s = ReadAll(p);
  const size_t data = s.find('_', s.find("<AppendedData")) + 1;
  const uint64_t nv = 5, nt = 2;
  const uint64_t payload = nv * (4 + 1 + 1 + 4 + 1 + 12) + nt * (1 + 16 + 4 + 1) + 10 * 8;
  EXPECT_EQ(s.size() - data, payload + std::string("\n  </AppendedData>\n</VTKFile>\n").size());
  EXPECT_NE(s.find("header_type=\"UInt64\""), std::string::npos);
  EXPECT_EQ(s.find("compressor"), std::string::npos);
}

TEST(MeshIo, WritersLeaveNoTemporaryFilesAndReplaceExistingFiles) {
  const TetMesh m = TwoTets();
  const fs::path dir = testing::MakeScratchDir("atomic");
  for (const char* name : {"m.vtu", "m.msh", "m.mesh"}) {
    WriteAll(dir / name, "old contents");
    ASSERT_TRUE(WriteMesh(m, dir / name).ok()) << name;
    EXPECT_NE(ReadAll(dir / name), "old contents");
  }
  int files = 0;
  for (const auto& e : fs::directory_iterator(dir)) {
    ++files;
    EXPECT_EQ(e.path().string().find(".tmp"), std::string::npos) << e.path();
  }
  EXPECT_EQ(files, 3);
}

TEST(MeshIo, WriteErrorsNameThePathAndLeaveNothingBehind) {
  const TetMesh m = TwoTets();
  const fs::path dir = testing::MakeScratchDir("write_errors");
  const fs::path missing = dir / "no_such_dir" / "m.vtu";
  for (const absl::Status& s :
       {WriteVtu(m, missing), WriteGmsh(m, missing), WriteMedit(m, missing)}) {
    EXPECT_FALSE(s.ok());
    EXPECT_NE(s.message().find(missing.string()), std::string::npos) << s;
  }
  absl::Status s = WriteMesh(m, dir / "m.stl");
  EXPECT_EQ(s.code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(s.message().find("m.stl"), std::string::npos) << s;

  TetMesh bad = m;
  bad.cell_regions.pop_back();
  s = WriteVtu(bad, dir / "bad.vtu");
  EXPECT_EQ(s.code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(s.message().find("cell_regions"), std::string::npos) << s;
  bad = m;
  bad.tets[5] = 9;
  s = WriteGmsh(bad, dir / "bad.msh");
  EXPECT_EQ(s.code(), absl::StatusCode::kInvalidArgument) << s;
  EXPECT_TRUE(fs::is_empty(dir));
}

TEST(MeshIo, MeditFileCarriesVertexLabelsAndRegionPlusOneReferences) {
  const TetMesh m = TwoTets();
  const fs::path p = testing::MakeScratchDir("medit") / "m.mesh";
  ASSERT_TRUE(WriteMedit(m, p).ok());
  const std::string expected =
      "MeshVersionFormatted 2\n\nDimension 3\n\nVertices\n5\n"
      "0 0 0 0\n1 0 0 0\n0 1 0 2\n0 0 1 2\n1 1 1 1\n\n"
      "Tetrahedra\n2\n1 2 3 4 1\n2 3 4 5 3\n\nEnd\n";
  EXPECT_EQ(ReadAll(p), expected);
}

// ---------------------------------------------------------------------------------------------
// Independent readers

struct VtkFacts {
  std::map<std::string, std::string> facts;
  double Num(const std::string& key) const {
    auto it = facts.find(key);
    return it == facts.end() ? std::nan("") : std::stod(it->second);
  }
};

void ExpectVtkSeesMesh(const std::string& python, const fs::path& file, const TetMesh& m) {
  auto [rc, out] =
      RunCommand(python + " " + Quote(Script("check_vtu.py")) + " stats " + Quote(file));
  ASSERT_EQ(rc, 0) << out;
  VtkFacts f{ParseFacts(out)};
  EXPECT_EQ(f.Num("points"), m.vertex_count()) << out;
  EXPECT_EQ(f.Num("cells"), m.tet_count());
  EXPECT_EQ(f.facts["cell_types"], "10");
  EXPECT_EQ(f.facts["points_type"], "float");
  EXPECT_NEAR(f.Num("points_abs_sum"), AbsSum(m.positions), 1e-9 * AbsSum(m.positions));
  EXPECT_NEAR(f.Num("total_volume"), TotalVolume(m), 1e-9 * TotalVolume(m));
  EXPECT_EQ(f.Num("connectivity_sum"), SumInt(m.tets));
  EXPECT_GT(f.Num("min_volume"), 0.0);
  EXPECT_EQ(f.facts["point_array scalar"], "float " + std::to_string(m.vertex_count()));
  EXPECT_EQ(f.facts["point_array label"], "unsigned char " + std::to_string(m.vertex_count()));
  EXPECT_EQ(f.facts["cell_array region"], "unsigned char " + std::to_string(m.tet_count()));
  EXPECT_NEAR(f.Num("sum_scalar"), Sum(m.scalars), 1e-6 * (1 + std::abs(Sum(m.scalars))));
  EXPECT_EQ(f.Num("sum_label"), SumInt(m.labels));
  EXPECT_EQ(f.Num("sum_region"), SumInt(m.cell_regions));
  double feature = 0, boundary = 0, infinite = 0;
  for (int64_t v = 0; v < m.vertex_count(); ++v) {
    feature += (m.vertex_flags[v] & kFeatureVertex) ? 1 : 0;
    boundary += (m.vertex_flags[v] & kExteriorBoundaryVertex) ? 1 : 0;
    infinite += std::isinf(m.interface_distance[v]) ? 1 : 0;
  }
  EXPECT_EQ(f.Num("sum_feature"), feature);
  EXPECT_EQ(f.Num("sum_boundary"), boundary);
  EXPECT_NEAR(f.Num("sum_interface_distance"), Sum(m.interface_distance),
              1e-6 * (1 + Sum(m.interface_distance)));
  EXPECT_EQ(f.Num("nonfinite_interface_distance"), infinite);
}

TEST(MeshIo, VtkReadsOurVtuFilesWithTheRightCountsAndValues) {
  const std::string python = PythonWithVtk();
  if (python.empty()) GTEST_SKIP() << "no python3 with the vtk module (Debian python3-vtk9)";
  const fs::path dir = testing::MakeScratchDir("vtk_reads");
  for (const TetMesh& m : {TwoTets(), PhantomMesh()}) {
    for (const VtuEncoding& e : kVtuEncodings) {
      const fs::path p = dir / e.file;
      ASSERT_TRUE(WriteVtu(m, p, e.options).ok());
      SCOPED_TRACE(p.string() + " with " + std::to_string(m.tet_count()) + " tets");
      ExpectVtkSeesMesh(python, p, m);
    }
  }
}

// The compact encoding (LZMA blocks with delta-coded offsets) is what VTK reads from the raw
// file of the same mesh, array for array and bit for bit (check_vtu.py same), with the region
// table as field data.
TEST(MeshIo, VtkReadsEveryCompressedVtuAsTheRawOneArrayForArray) {
  const std::string python = PythonWithVtk();
  if (python.empty()) GTEST_SKIP() << "no python3 with the vtk module (Debian python3-vtk9)";
  const fs::path dir = testing::MakeScratchDir("vtk_same");
  const TetMesh m = PhantomMesh();
  RegionTable table;
  for (int r = 0; r < 3; ++r) {
    RegionInfo& info = table.regions.emplace_back();
    info.label = static_cast<uint8_t>(r);
    info.name = std::string("region \"") + char('a' + r) + "\"";
    info.rgb = {static_cast<uint8_t>(40 * r), 159, 66};
  }
  for (VtuEncoding e : kVtuEncodings) {
    e.options.regions = &table;
    // Several blocks per array (1 MiB each) and both thread counts.
    e.options.threads = 2;
    ASSERT_TRUE(WriteVtu(m, dir / e.file, e.options).ok());
  }
  for (const char* file : {"zlib.vtu", "lzma.vtu"}) {
    auto [rc, log] = RunCommand(python + " " + Quote(Script("check_vtu.py")) + " same " +
                                Quote(dir / "raw.vtu") + " " + Quote(dir / file));
    EXPECT_EQ(rc, 0) << file << ": " << log;
    EXPECT_EQ(log, "same\n") << file;
  }
  EXPECT_NE(ReadAll(dir / "lzma.vtu").find("compressor=\"vtkLZMADataCompressor\""),
            std::string::npos);
}

TEST(MeshIo, ReadVtuReadsEveryEncodingVtkWrites) {
  const std::string python = PythonWithVtk();
  if (python.empty()) GTEST_SKIP() << "no python3 with the vtk module (Debian python3-vtk9)";
  const fs::path dir = testing::MakeScratchDir("vtk_writes");
  const TetMesh m = PhantomMesh({9, 8, 7});
  const fs::path src = dir / "ours.vtu";
  ASSERT_TRUE(WriteVtu(m, src).ok());
  auto [rc, log] = RunCommand(python + " " + Quote(Script("check_vtu.py")) + " rewrite " +
                              Quote(src) + " " + Quote(dir));
  ASSERT_EQ(rc, 0) << log;
  std::istringstream lines(log);
  std::string word, file;
  int files = 0;
  while (lines >> word >> file) {
    ASSERT_EQ(word, "written") << log;
    ++files;
    auto back = ReadVtu(file);
    ASSERT_TRUE(back.ok()) << file << ": " << back.status();
    SCOPED_TRACE(file);
    ExpectSameMesh(m, *back);
  }
  EXPECT_EQ(files, 20) << log;  // 4 modes x 3 compressors x 2 headers, minus compressed ascii
}

// VTK's quadric decimation renames the field to "scalars" (and drops every other array): the
// reader must take that array as the field, not default it to zeros.
TEST(MeshIo, ReadVtuTakesTheFieldVtkDecimationWrites) {
  const std::string python = PythonWithVtk();
  if (python.empty()) GTEST_SKIP() << "no python3 with the vtk module (Debian python3-vtk9)";
  const fs::path dir = testing::MakeScratchDir("vtk_decimates");
  const TetMesh m = PhantomMesh({9, 8, 7});
  const fs::path src = dir / "ours.vtu", dst = dir / "vtk.vtu";
  ASSERT_TRUE(WriteVtu(m, src).ok());
  auto [rc, log] = RunCommand(python + " " + Quote(Script("check_vtu.py")) + " decimate " +
                              Quote(src) + " " + Quote(dst) + " 0.3");
  ASSERT_EQ(rc, 0) << log;
  auto [src_rc, out] =
      RunCommand(python + " " + Quote(Script("check_vtu.py")) + " stats " + Quote(dst));
  ASSERT_EQ(src_rc, 0) << out;
  const VtkFacts f{ParseFacts(out)};
  ASSERT_NE(f.facts.count("point_array scalars"), 0u) << "VTK no longer renames the field";
  VtuReadReport report;
  auto back = ReadVtu(dst, &report);
  ASSERT_TRUE(back.ok()) << back.status();
  EXPECT_EQ(report.scalar_array, "scalars");
  EXPECT_FALSE(report.has_labels);
  EXPECT_FALSE(report.has_regions);
  EXPECT_EQ(back->tet_count(), f.Num("cells"));
  EXPECT_LT(back->tet_count(), m.tet_count());
  // VTK writes the field as Float64; ours is Float32, hence the relative tolerance.
  EXPECT_NEAR(Sum(back->scalars), f.Num("sum_scalars"), 1e-6 * std::abs(f.Num("sum_scalars")));
  EXPECT_GT(*std::max_element(back->scalars.begin(), back->scalars.end()), 500.0f);
}

struct GmshFacts {
  std::map<std::string, std::string> facts;
  double Num(const std::string& key) const {
    auto it = facts.find(key);
    return it == facts.end() ? -1 : std::stod(it->second);
  }
};

void ExpectGmshSeesMesh(const GmshFacts& f, const TetMesh& m) {
  EXPECT_EQ(f.Num("nodes"), m.vertex_count());
  EXPECT_EQ(f.Num("tets"), m.tet_count());
  EXPECT_EQ(f.Num("other_elements"), 0);
  EXPECT_NEAR(f.Num("coord_abs_sum"), AbsSum(m.positions), 1e-6 * AbsSum(m.positions));
  EXPECT_NEAR(f.Num("tet_coord_abs_sum"), TetCoordAbsSum(m), 1e-6 * TetCoordAbsSum(m));
  EXPECT_GT(f.Num("min_volume"), 0);
  EXPECT_NEAR(f.Num("total_volume"), TotalVolume(m), 1e-6 * TotalVolume(m));
}

GmshFacts RunGmsh(const std::string& python, const std::string& gmsh, const fs::path& file) {
  auto [rc, out] = RunCommand(python + " " + Quote(Script("check_gmsh.py")) + " " + gmsh + " " +
                              Quote(file) + " " + Quote(file.string() + ".v22.msh"));
  EXPECT_EQ(rc, 0) << out;
  return {ParseFacts(out)};
}

TEST(MeshIo, GmshReadsOurMshWithRegionsAsPhysicalGroups) {
  const std::string gmsh = GmshBinary();
  if (gmsh.empty()) GTEST_SKIP() << "gmsh not found on PATH (Debian package gmsh)";
  const std::string python = AnyPython();
  if (python.empty()) GTEST_SKIP() << "no python3 to run check_gmsh.py";
  const fs::path dir = testing::MakeScratchDir("gmsh_msh");
  for (const TetMesh& m : {TwoTets(), PhantomMesh()}) {
    std::map<int, int64_t> per_region;
    for (uint8_t r : m.cell_regions) ++per_region[r];
    for (bool binary : {true, false}) {
      const fs::path p = dir / (binary ? "bin.msh" : "ascii.msh");
      ASSERT_TRUE(WriteGmsh(m, p, {.binary = binary}).ok());
      SCOPED_TRACE(p.string() + " with " + std::to_string(m.tet_count()) + " tets");
      const GmshFacts f = RunGmsh(python, gmsh, p);
      ExpectGmshSeesMesh(f, m);
      for (const auto& [r, n] : per_region) {
        EXPECT_EQ(f.Num("physical " + std::to_string(r + 1)), n) << "region " << r;
        EXPECT_EQ(f.Num("elementary " + std::to_string(r + 1)), n) << "region " << r;
        EXPECT_EQ(f.facts.at("name " + std::to_string(r + 1)), "3 region_" + std::to_string(r));
      }
    }
  }
}

RegionTable NamedRegions(const TetMesh& m) {
  int k = 0;
  for (uint8_t r : m.cell_regions) k = std::max(k, r + 1);
  std::vector<std::string> names = {"air", "soft \"tissue\"", "bone", "Gehirn \xC3\xBC"};
  names.resize(std::max(k, 1));
  for (int r = 4; r < k; ++r) names[r] = "r" + std::to_string(r);
  RegionTable t;
  EXPECT_TRUE(MakeRegionTable(std::vector<double>(names.size(), 0),
                              std::vector<int64_t>(names.size(), 1), false, names, &t)
                  .ok());
  return t;
}

// The region table as field data: VTK reads back every name (UTF-8 too), label and colour, and
// ReadVtu still reads the file.
TEST(MeshIo, VtkReadsTheRegionNamesAndColoursFromTheVtuFieldData) {
  const std::string python = PythonWithVtk();
  if (python.empty()) GTEST_SKIP() << "no python3 with the vtk module (Debian python3-vtk9)";
  const fs::path dir = testing::MakeScratchDir("vtu_regions");
  const TetMesh m = PhantomMesh();
  const RegionTable t = NamedRegions(m);
  ASSERT_GE(t.regions.size(), 3u);
  for (bool compress : {false, true}) {
    const fs::path p = dir / (compress ? "z.vtu" : "raw.vtu");
    ASSERT_TRUE(WriteVtu(m, p, {.compress = compress, .regions = &t}).ok());
    auto [rc, out] =
        RunCommand(python + " " + Quote(Script("check_vtu.py")) + " stats " + Quote(p));
    ASSERT_EQ(rc, 0) << out;
    const auto f = ParseFacts(out);
    for (size_t r = 0; r < t.regions.size(); ++r) {
      const std::string i = std::to_string(r);
      EXPECT_EQ(f.at("field_region_names_" + i), t.regions[r].name) << out;
      EXPECT_EQ(f.at("field_region_labels_" + i), i);
      const auto& c = t.regions[r].rgb;
      EXPECT_EQ(f.at("field_region_colors_" + i),
                std::to_string(c[0]) + "," + std::to_string(c[1]) + "," + std::to_string(c[2]));
    }
    auto back = ReadVtu(p);
    ASSERT_TRUE(back.ok()) << back.status();
    EXPECT_EQ(back->cell_regions, m.cell_regions);
  }
}

TEST(MeshIo, GmshReadsTheRegionNamesAsPhysicalNames) {
  const std::string gmsh = GmshBinary();
  if (gmsh.empty()) GTEST_SKIP() << "gmsh not found on PATH (Debian package gmsh)";
  const std::string python = AnyPython();
  if (python.empty()) GTEST_SKIP() << "no python3 to run check_gmsh.py";
  const fs::path dir = testing::MakeScratchDir("gmsh_names");
  const TetMesh m = PhantomMesh();
  const RegionTable t = NamedRegions(m);
  std::set<int> present(m.cell_regions.begin(), m.cell_regions.end());
  for (bool binary : {true, false}) {
    const fs::path p = dir / (binary ? "bin.msh" : "ascii.msh");
    ASSERT_TRUE(WriteGmsh(m, p, {.binary = binary, .regions = &t}).ok());
    const GmshFacts f = RunGmsh(python, gmsh, p);
    for (int r : present) {
      std::string want = t.regions[r].name;
      std::replace(want.begin(), want.end(), '"', '\'');  // a quote would end Gmsh's string
      EXPECT_EQ(f.facts.at("name " + std::to_string(r + 1)), "3 " + want) << p;
    }
  }
}

// The region surfaces of a noisy phantom (its labels touch themselves diagonally in places) as
// STL: VTK's reader joins vertices by position, as slicers do, and still finds every surface
// closed and 2-manifold, with every triangle.
TEST(MeshIo, VtkFindsTheRegionSurfacesClosedAndManifold) {
  const std::string python = PythonWithVtk();
  if (python.empty()) GTEST_SKIP() << "no python3 with the vtk module (Debian python3-vtk9)";
  const fs::path dir = testing::MakeScratchDir("stl");
  const TetMesh m = PhantomMesh();
  const auto surfaces = ExtractRegionSurfaces(m);
  ASSERT_EQ(surfaces.size(), 3u);
  for (const RegionSurface& s : surfaces) {
    const fs::path p = dir / ("surface-" + std::to_string(s.region) + ".stl");
    ASSERT_TRUE(WriteStl(s, "region " + std::to_string(s.region), p).ok());
    auto [rc, log] = RunCommand(python + " " + Quote(Script("check_surfaces.py")) + " " + Quote(p));
    ASSERT_EQ(rc, 0) << log;
    std::istringstream in(log);
    std::string path, k1, k2, k3;
    int64_t triangles = -1, boundary = -1, non_manifold = -1;
    in >> path >> k1 >> triangles >> k2 >> boundary >> k3 >> non_manifold;
    EXPECT_EQ(triangles, s.triangle_count()) << log;
    EXPECT_EQ(boundary, 0) << log;
    EXPECT_EQ(non_manifold, 0) << log;
  }
}

// The same surfaces in one .glb: VTK's glTF reader finds each region's mesh with its counts.
TEST(MeshIo, VtkReadsTheRegionSurfacesFromOneGlb) {
  const std::string python = PythonWithVtk();
  if (python.empty()) GTEST_SKIP() << "no python3 with the vtk module (Debian python3-vtk9)";
  const fs::path dir = testing::MakeScratchDir("glb");
  const auto surfaces = ExtractRegionSurfaces(PhantomMesh());
  const fs::path p = dir / "surfaces.glb";
  ASSERT_TRUE(WriteGlb(surfaces, {}, p).ok());
  auto [rc, log] = RunCommand(python + " " + Quote(Script("check_surfaces.py")) + " " + Quote(p));
  ASSERT_EQ(rc, 0) << log;
  EXPECT_NE(log.find("meshes " + std::to_string(surfaces.size())), std::string::npos) << log;
  for (size_t i = 0; i < surfaces.size(); ++i) {
    EXPECT_NE(log.find("mesh " + std::to_string(i) + " points " +
                       std::to_string(surfaces[i].vertex_count()) + " triangles " +
                       std::to_string(surfaces[i].triangle_count())),
              std::string::npos)
        << log;
  }
}

TEST(MeshIo, GmshReadsOurMeditFileWithRegionsAsReferences) {
  const std::string gmsh = GmshBinary();
  if (gmsh.empty()) GTEST_SKIP() << "gmsh not found on PATH (Debian package gmsh)";
  const std::string python = AnyPython();
  if (python.empty()) GTEST_SKIP() << "no python3 to run check_gmsh.py";
  const fs::path dir = testing::MakeScratchDir("gmsh_medit");
  for (const TetMesh& m : {TwoTets(), PhantomMesh()}) {
    std::map<int, int64_t> per_region;
    for (uint8_t r : m.cell_regions) ++per_region[r];
    const fs::path p = dir / "m.mesh";
    ASSERT_TRUE(WriteMedit(m, p).ok());
    const GmshFacts f = RunGmsh(python, gmsh, p);
    ExpectGmshSeesMesh(f, m);
    ASSERT_GE(per_region.size(), m.tet_count() > 2 ? 3u : 2u);
    // Gmsh turns MEDIT references into elementary entities: one per region, not all "1".
    for (const auto& [r, n] : per_region)
      EXPECT_EQ(f.Num("elementary " + std::to_string(r + 1)), n) << "region " << r;
  }
}

// ---------------------------------------------------------------------------------------------
// Broken .vtu files

class BrokenVtu : public ::testing::Test {
 protected:
  void SetUp() override {
    dir_ = testing::MakeScratchDir("broken_vtu");
    ASSERT_TRUE(WriteVtu(TwoTets(), dir_ / "raw.vtu", {.compress = false}).ok());
    ASSERT_TRUE(
        WriteVtu(TwoTets(), dir_ / "z.vtu", {.compress = true, .compressor = VtuCompressor::kZlib})
            .ok());
    ASSERT_TRUE(
        WriteVtu(TwoTets(), dir_ / "xz.vtu", {.compress = true, .compressor = VtuCompressor::kLzma})
            .ok());
    raw_ = ReadAll(dir_ / "raw.vtu");
    z_ = ReadAll(dir_ / "z.vtu");
    xz_ = ReadAll(dir_ / "xz.vtu");
  }
  // The offset="..." attribute of array `name` in the XML of `file`.
  static std::string OffsetAttr(const std::string& file, const std::string& name) {
    const size_t at = file.find("Name=\"" + name + "\"");
    EXPECT_NE(at, std::string::npos) << name;
    const size_t b = file.find("offset=\"", at) + 8;
    return file.substr(b, file.find('"', b) - b);
  }
  // Byte position in `file` of the data (after the size header) of array `name`.
  static size_t DataPos(const std::string& file, const std::string& name, size_t header = 8) {
    return file.find('_', file.find("<AppendedData")) + 1 + std::stoul(OffsetAttr(file, name)) +
           header;
  }
  // Writes `bytes`, reads it back, expects failure with `code` and `needle` in the message.
  void ExpectError(const std::string& bytes, absl::StatusCode code, const std::string& needle) {
    const fs::path p = dir_ / ("case" + std::to_string(case_++) + ".vtu");
    WriteAll(p, bytes);
    auto m = ReadVtu(p);
    ASSERT_FALSE(m.ok()) << "expected an error containing '" << needle << "'";
    EXPECT_EQ(m.status().code(), code) << m.status();
    EXPECT_NE(m.status().message().find(needle), std::string::npos) << m.status();
    EXPECT_NE(m.status().message().find(p.string()), std::string::npos) << m.status();
  }
  static std::string Replace(std::string s, const std::string& from, const std::string& to) {
    const size_t at = s.find(from);
    EXPECT_NE(at, std::string::npos) << from;
    return s.replace(at, from.size(), to);
  }
  template <typename T>
  static std::string Poke(std::string s, size_t pos, T value) {
    std::memcpy(s.data() + pos, &value, sizeof(T));
    return s;
  }

  fs::path dir_;
  std::string raw_, z_, xz_;
  int case_ = 0;
};

TEST_F(BrokenVtu, MissingFileIsNotFound) {
  auto m = ReadVtu(dir_ / "nope.vtu");
  EXPECT_EQ(m.status().code(), absl::StatusCode::kNotFound) << m.status();
}

TEST_F(BrokenVtu, NonXmlAndMalformedXmlAreRejected) {
  const auto kInvalid = absl::StatusCode::kInvalidArgument;
  ExpectError("", kInvalid, "no root element");
  ExpectError("hello world", kInvalid, "text outside the root");
  ExpectError(std::string("\x1f\x8b\x08\x00", 4), kInvalid, "gzip");
  ExpectError("<VTKFile type=\"UnstructuredGrid\"><UnstructuredGrid>", kInvalid, "end of file");
  ExpectError("<VTKFile type=\"UnstructuredGrid\"></Other>", kInvalid, "unexpected end tag");
  ExpectError("<VTKFile type=UnstructuredGrid/>", kInvalid, "not quoted");
  ExpectError("<VTKFile a=\"1\" a=\"2\"/>", kInvalid, "duplicate attribute");
  ExpectError("<PolyData/>", kInvalid, "expected <VTKFile>");
  ExpectError(Replace(raw_, "type=\"UnstructuredGrid\"", "type=\"PolyData\""), kInvalid,
              "'PolyData'");
  ExpectError(Replace(raw_, "<Piece", "<Pizza"), kInvalid, "unexpected end tag </Piece>");
  ExpectError(Replace(raw_, "<Points>", "<Pointz>"), kInvalid, "unexpected end tag");
}

TEST_F(BrokenVtu, UnsupportedVtkFeaturesAreUnimplemented) {
  const auto kUnimplemented = absl::StatusCode::kUnimplemented;
  ExpectError(Replace(raw_, "LittleEndian", "BigEndian"), kUnimplemented, "big-endian");
  ExpectError(Replace(z_, "vtkZLibDataCompressor", "vtkLZ4DataCompressor"), kUnimplemented,
              "vtkLZ4DataCompressor");
  std::string two = raw_;
  const size_t begin = two.find("<Piece"), end = two.find("</Piece>") + 8;
  two.insert(end, two.substr(begin, end - begin));
  ExpectError(two, kUnimplemented, "2 pieces");
}

TEST_F(BrokenVtu, CountsThatDisagreeWithArraySizesAreRejected) {
  const auto kInvalid = absl::StatusCode::kInvalidArgument;
  ExpectError(Replace(raw_, "NumberOfPoints=\"5\"", "NumberOfPoints=\"6\""), kInvalid,
              "DataArray 'Points': holds 60 bytes, expected 72");
  ExpectError(Replace(z_, "NumberOfCells=\"2\"", "NumberOfCells=\"1\""), kInvalid,
              "DataArray 'types': holds 2 bytes, expected 1");
  ExpectError(Replace(raw_, "NumberOfPoints=\"5\"", "NumberOfPoints=\"-5\""), kInvalid,
              "NumberOfPoints is missing or not a count");
  ExpectError(Replace(raw_, "NumberOfCells=\"2\"", "NumberOfCells=\"99999999999\""), kInvalid,
              "exceeds the limit");
  ExpectError(Replace(raw_, "Name=\"Points\" NumberOfComponents=\"3\"", "Name=\"Points\""),
              kInvalid, "has 1 components, expected 3");
}

TEST_F(BrokenVtu, HugeClaimedSizesFailBeforeAllocating) {
  const auto kInvalid = absl::StatusCode::kInvalidArgument;
  // 2e9 points would be 24 GB of positions: rejected because the file cannot hold them.
  ExpectError(Replace(raw_, "NumberOfPoints=\"5\"", "NumberOfPoints=\"2000000000\""), kInvalid,
              "DataArray 'Points'");
  ExpectError(Replace(z_, "NumberOfPoints=\"5\"", "NumberOfPoints=\"2000000000\""), kInvalid,
              "DataArray 'Points'");
  // A raw size header of 10^15 bytes.
  ExpectError(Poke<uint64_t>(raw_, DataPos(raw_, "Points") - 8, 1'000'000'000'000'000), kInvalid,
              "holds 1000000000000000 bytes");
  // A zlib header claiming 10^12 blocks.
  ExpectError(Poke<uint64_t>(z_, DataPos(z_, "Points", 0), 1'000'000'000'000), kInvalid,
              "truncated: compression header claims 1000000000000 blocks");
  // A zlib block that would have to inflate 768 KiB (65536 points) from 3 bytes.
  const size_t h = DataPos(z_, "Points", 0);
  std::string bomb = Replace(z_, "NumberOfPoints=\"5\"", "NumberOfPoints=\"65536\"");
  const size_t shift = bomb.size() - z_.size();
  bomb = Poke<uint64_t>(bomb, h + shift + 8, 12 * 65536);  // block size
  bomb = Poke<uint64_t>(bomb, h + shift + 16, 0);          // last block is full
  bomb = Poke<uint64_t>(bomb, h + shift + 24, 3);          // compressed size
  ExpectError(bomb, kInvalid, "impossible ratio");
}

TEST_F(BrokenVtu, TruncatedFilesAndBadOffsetsAreRejected) {
  const auto kInvalid = absl::StatusCode::kInvalidArgument;
  ExpectError(raw_.substr(0, DataPos(raw_, "Points") + 5), kInvalid,
              "truncated: holds 60 bytes but only 5 remain");
  ExpectError(z_.substr(0, DataPos(z_, "Points", 0) + 30), kInvalid, "truncated");
  ExpectError(z_.substr(0, DataPos(z_, "Points", 0) + 40), kInvalid, "truncated");
  ExpectError(raw_.substr(0, raw_.find("<AppendedData")), kInvalid, "end of file inside <VTKFile>");
  const std::string types = "Name=\"types\" format=\"appended\" offset=\"";
  ExpectError(Replace(raw_, types + OffsetAttr(raw_, "types"), types + "123456789"), kInvalid,
              "beyond the end of the file");
  ExpectError(Replace(raw_, "encoding=\"raw\"", "encoding=\"hex\""), kInvalid, "'hex'");
  ExpectError(Replace(raw_, "   _", "   ~"), kInvalid, "'_' marker");
}

TEST_F(BrokenVtu, CorruptZlibBlockIsRejected) {
  std::string bad = z_;
  const size_t pos = DataPos(z_, "Points", 8 * 4);  // 4 header words for one block
  for (int i = 2; i < 12; ++i) bad[pos + i] = static_cast<char>(bad[pos + i] ^ 0x5a);
  ExpectError(bad, absl::StatusCode::kInvalidArgument, "zlib block 0 is corrupt");
}

TEST_F(BrokenVtu, CorruptLzmaBlockIsRejected) {
  std::string bad = xz_;
  const size_t pos = DataPos(xz_, "Points", 8 * 4);  // 4 header words for one block
  // Past the 12-byte .xz stream header, into the block (its header, data or CRC64).
  for (int i = 14; i < 24; ++i) bad[pos + i] = static_cast<char>(bad[pos + i] ^ 0x5a);
  ExpectError(bad, absl::StatusCode::kInvalidArgument, "LZMA block 0 is corrupt");
  // The compressor attribute decides: an .xz stream read as zlib is corrupt.
  ExpectError(
      Replace(xz_, "compressor=\"vtkLZMADataCompressor\"", "compressor=\"vtkZLibDataCompressor\""),
      absl::StatusCode::kInvalidArgument, "zlib block 0 is corrupt");
}

TEST_F(BrokenVtu, BadCellsAreRejected) {
  const auto kInvalid = absl::StatusCode::kInvalidArgument;
  ExpectError(Poke<uint8_t>(raw_, DataPos(raw_, "types") + 1, 5), absl::StatusCode::kUnimplemented,
              "cell 1 has VTK cell type 5");
  ExpectError(Poke<int32_t>(raw_, DataPos(raw_, "connectivity") + 4 * 6, 5), kInvalid,
              "cell 1 references point 5");
  ExpectError(Poke<int32_t>(raw_, DataPos(raw_, "connectivity") + 4 * 6, -1), kInvalid,
              "cell 1 references point -1");
  ExpectError(Poke<int32_t>(raw_, DataPos(raw_, "connectivity") + 4 * 1, 0), kInvalid,
              "cell 0 uses point 0 twice");
  std::string swapped = Poke<int32_t>(raw_, DataPos(raw_, "connectivity") + 4 * 0, 1);
  swapped = Poke<int32_t>(swapped, DataPos(raw_, "connectivity") + 4 * 1, 0);
  ExpectError(swapped, kInvalid, "cell 0 is inverted");
  // Measuring another tool's output may keep such cells, counted.
  const fs::path p = dir_ / "inverted.vtu";
  WriteAll(p, swapped);
  VtuReadReport report;
  auto kept = ReadVtu(p, &report, {.allow_inverted_cells = true});
  ASSERT_TRUE(kept.ok()) << kept.status();
  EXPECT_EQ(report.inverted_or_flat_cells, 1);
  EXPECT_LT(TetVolume(*kept, 0), 0);
  EXPECT_EQ(kept->tet_count(), 2);
  ExpectError(Poke<int32_t>(raw_, DataPos(raw_, "offsets"), 3), kInvalid,
              "'offsets' entry 0 is 3, expected 4");
}

TEST_F(BrokenVtu, BadValuesAreRejected) {
  const auto kInvalid = absl::StatusCode::kInvalidArgument;
  ExpectError(Poke<float>(raw_, DataPos(raw_, "Points") + 4, std::nanf("")), kInvalid,
              "point 0 has a non-finite coordinate");
  ExpectError(Poke<float>(raw_, DataPos(raw_, "scalar") + 8, kInf), kInvalid,
              "point 2 has a non-finite scalar");
  ExpectError(Poke<uint8_t>(raw_, DataPos(raw_, "label") + 3, 8), kInvalid, "point 3 has label 8");
  ExpectError(Poke<uint8_t>(raw_, DataPos(raw_, "region") + 1, 200), kInvalid,
              "cell 1 has region 200");
  ExpectError(Replace(raw_, "type=\"Float32\" Name=\"scalar\"", "type=\"Float33\" Name=\"scalar\""),
              kInvalid, "type 'Float33'");
}

// Removes the DataArray named `name` (its whole element) from the XML of `s`.
std::string EraseArray(std::string s, const std::string& name) {
  const size_t at = s.find("Name=\"" + name + "\"");
  EXPECT_NE(at, std::string::npos) << name;
  const size_t b = s.rfind('<', at), e = s.find('>', at) + 1;
  return s.erase(b, e - b);
}

TEST_F(BrokenVtu, OptionalArraysDefaultWhenMissingAndTheReportSaysSo) {
  std::string s = raw_;
  for (const char* name : {"label", "feature", "interface_distance", "boundary", "region"})
    s = EraseArray(s, name);
  const fs::path p = dir_ / "bare.vtu";
  WriteAll(p, s);
  VtuReadReport report;
  report.has_labels = report.has_regions = true;  // must be overwritten
  auto m = ReadVtu(p, &report);
  ASSERT_TRUE(m.ok()) << m.status();
  const TetMesh ref = TwoTets();
  EXPECT_EQ(m->positions, ref.positions);
  EXPECT_EQ(m->tets, ref.tets);
  EXPECT_EQ(m->scalars, ref.scalars);
  EXPECT_EQ(m->labels, std::vector<uint8_t>(5, 0));
  EXPECT_EQ(m->interface_distance, std::vector<float>(5, kInf));
  EXPECT_EQ(m->vertex_flags, std::vector<uint8_t>(5, 0));
  EXPECT_EQ(m->cell_regions, std::vector<uint8_t>(2, 0));
  EXPECT_EQ(report.scalar_array, "scalar");
  EXPECT_FALSE(report.has_labels);
  EXPECT_FALSE(report.has_interface_distance);
  EXPECT_FALSE(report.has_vertex_flags);
  EXPECT_FALSE(report.has_regions);

  VtuReadReport full;
  ASSERT_TRUE(ReadVtu(dir_ / "raw.vtu", &full).ok());
  EXPECT_TRUE(full.has_labels && full.has_interface_distance && full.has_vertex_flags &&
              full.has_regions);
}

TEST_F(BrokenVtu, FieldIsTheActiveScalarsWhateverTheirName) {
  // As VTK's filters write it: the field renamed "scalars" and marked active.
  std::string s = Replace(raw_, "Name=\"scalar\"", "Name=\"scalars\"");
  s = Replace(s, "Scalars=\"scalar\"", "Scalars=\"scalars\"");
  const fs::path p = dir_ / "scalars.vtu";
  WriteAll(p, s);
  VtuReadReport report;
  auto m = ReadVtu(p, &report);
  ASSERT_TRUE(m.ok()) << m.status();
  EXPECT_EQ(m->scalars, TwoTets().scalars);
  EXPECT_EQ(report.scalar_array, "scalars");

  // The active array wins over one named "scalar": the file says which one is the field.
  std::string label_active = Replace(raw_, "Scalars=\"scalar\"", "Scalars=\"label\"");
  WriteAll(p, label_active);
  m = ReadVtu(p, &report);
  ASSERT_TRUE(m.ok()) << m.status();
  EXPECT_EQ(m->scalars, std::vector<float>({0, 0, 2, 2, 1}));
  EXPECT_EQ(report.scalar_array, "label");
}

TEST_F(BrokenVtu, OnlyPointArrayIsTheField) {
  std::string s = raw_;
  for (const char* name : {"label", "feature", "interface_distance", "boundary"})
    s = EraseArray(s, name);
  s = Replace(s, " Scalars=\"scalar\"", "");
  s = Replace(s, "Name=\"scalar\"", "Name=\"intensity\"");
  const fs::path p = dir_ / "only.vtu";
  WriteAll(p, s);
  VtuReadReport report;
  auto m = ReadVtu(p, &report);
  ASSERT_TRUE(m.ok()) << m.status();
  EXPECT_EQ(m->scalars, TwoTets().scalars);
  EXPECT_EQ(report.scalar_array, "intensity");

  // The only point array without a Name (found by vtu_fuzz): the report could not say which
  // array the field came from, so it is an error naming the attribute, not a nameless field.
  for (const char* unnamed : {"Nime=\"intensity\"", "Name=\"\""}) {
    SCOPED_TRACE(unnamed);
    WriteAll(p, Replace(s, "Name=\"intensity\"", unnamed));
    m = ReadVtu(p, &report);
    ASSERT_FALSE(m.ok());
    EXPECT_EQ(m.status().code(), absl::StatusCode::kInvalidArgument);
    EXPECT_NE(m.status().message().find("no Name"), absl::string_view::npos) << m.status();
  }
}

TEST_F(BrokenVtu, FileWithoutAnIdentifiableFieldIsAnErrorNotZeros) {
  const auto kInvalid = absl::StatusCode::kInvalidArgument;
  // The active scalars name an array that is not there.
  ExpectError(EraseArray(raw_, "scalar"), kInvalid,
              "PointData names 'scalar' as its active scalars, but has no DataArray");
  // Several arrays, none active, none named "scalar".
  std::string two = Replace(raw_, " Scalars=\"scalar\"", "");
  two = Replace(two, "Name=\"scalar\"", "Name=\"scalars\"");
  ExpectError(two, kInvalid, "cannot tell which point array is the field");
  ExpectError(two, kInvalid, "5 arrays ('scalars', 'label', 'feature'");
  // No point array at all.
  std::string none = Replace(raw_, " Scalars=\"scalar\"", "");
  for (const char* name : {"scalar", "label", "feature", "interface_distance", "boundary"})
    none = EraseArray(none, name);
  ExpectError(none, kInvalid, "PointData has no DataArray");
  // An active array of vectors is not a field.
  ExpectError(Replace(raw_, "Scalars=\"scalar\"", "Scalars=\"Points\""), kInvalid,
              "active scalars, but has no DataArray");
}

}  // namespace
}  // namespace decima
