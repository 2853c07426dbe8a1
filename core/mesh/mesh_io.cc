// Mesh writers (.vtu, .msh 4.1, .mesh) and the .vtu reader.
//
// Formats as specified by their owners: VTK's "VTK File Formats" (XML section; appended data
// with a UInt64 byte-count header, vtkZLibDataCompressor / vtkLZMADataCompressor block header
// [nblocks, block size, last partial block size, compressed size of each block]; an LZMA block
// is one .xz stream, as vtkLZMADataCompressor writes and decodes them), Gmsh's
// reference manual section "MSH file format" version 4.1, and the MEDIT/INRIA ".mesh" ASCII
// layout. Large arrays go to disk with one fwrite each; text formats are formatted with
// std::to_chars into one reusable buffer (no per-element allocation, no iostreams).
#include "core/mesh/mesh_io.h"

#include <fcntl.h>
#include <lzma.h>
#include <sys/stat.h>
#include <unistd.h>
#include <zlib.h>

#include <algorithm>
#include <array>
#include <atomic>
#include <cerrno>
#include <charconv>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <functional>
#include <limits>
#include <string>
#include <string_view>
#include <vector>

#include "absl/strings/str_cat.h"
#include "core/common/atomic_file.h"
#include "core/common/parallel.h"
#include "core/common/status.h"

namespace decima {
namespace {

constexpr uint8_t kVtkTetra = 10;
constexpr uint64_t kVtuBlockBytes = uint64_t{1} << 20;  // zlib block (VTK uses 32 KiB; any works)

std::string PathString(const std::filesystem::path& path) { return path.string(); }

// Checks the size invariants of tet_mesh.h that a writer relies on (indices are checked too, so a
// file never references a missing vertex).
absl::Status CheckMeshForWriting(const TetMesh& m, const std::filesystem::path& path) {
  const size_t nv = m.scalars.size();
  auto bad = [&](absl::string_view field, size_t got, size_t want) {
    return absl::InvalidArgumentError(absl::StrCat("cannot write ", PathString(path), ": mesh ",
                                                   field, " has ", got, " entries, expected ",
                                                   want));
  };
  if (m.positions.size() != 3 * nv) return bad("positions", m.positions.size(), 3 * nv);
  if (m.labels.size() != nv) return bad("labels", m.labels.size(), nv);
  if (m.interface_distance.size() != nv)
    return bad("interface_distance", m.interface_distance.size(), nv);
  if (m.vertex_flags.size() != nv) return bad("vertex_flags", m.vertex_flags.size(), nv);
  if (m.tets.size() % 4 != 0) return bad("tets", m.tets.size(), m.tets.size() / 4 * 4);
  if (m.cell_regions.size() != m.tets.size() / 4)
    return bad("cell_regions", m.cell_regions.size(), m.tets.size() / 4);
  if (nv > static_cast<size_t>(std::numeric_limits<int32_t>::max()))
    return absl::InvalidArgumentError(
        absl::StrCat("cannot write ", PathString(path), ": ", nv, " vertices exceed int32"));
  for (size_t i = 0; i < m.tets.size(); ++i) {
    if (m.tets[i] < 0 || static_cast<size_t>(m.tets[i]) >= nv)
      return absl::InvalidArgumentError(absl::StrCat("cannot write ", PathString(path), ": tet ",
                                                     i / 4, " references vertex ", m.tets[i],
                                                     " of ", nv));
  }
  return absl::OkStatus();
}

// Text formatting into one reusable buffer, flushed to an AtomicFile when full.
class TextWriter {
 public:
  explicit TextWriter(AtomicFile* file) : file_(file) { buf_.reserve(kCapacity + 256); }

  absl::Status Str(std::string_view s) {
    buf_.append(s);
    return MaybeFlush();
  }
  // A number followed by `sep`: integers exactly, reals as the shortest decimal text that
  // parses back to the same value.
  template <typename T>
  absl::Status Number(T v, char sep) {
    char tmp[40];
    auto r = std::to_chars(tmp, tmp + sizeof(tmp), v);
    buf_.append(tmp, r.ptr);
    buf_.push_back(sep);
    return MaybeFlush();
  }
  absl::Status Flush() {
    absl::Status s = file_->Write(buf_);
    buf_.clear();
    return s;
  }

 private:
  static constexpr size_t kCapacity = size_t{1} << 20;
  absl::Status MaybeFlush() { return buf_.size() >= kCapacity ? Flush() : absl::OkStatus(); }
  AtomicFile* file_;
  std::string buf_;
};

template <typename T>
const uint8_t* Bytes(const std::vector<T>& v) {
  return reinterpret_cast<const uint8_t*>(v.data());
}

// ---------------------------------------------------------------------------------------------
// .vtu writer

struct VtuArray {
  const char* section;  // "PointData", "CellData", "Points", "Cells"
  const char* type;     // VTK type name
  const char* name;
  int components;
  const uint8_t* data;  // nullptr: made a block at a time by `fill`
  uint64_t bytes;
  // LZMA only: the distance of xz's delta filter in bytes (0: none). The cell offsets are an
  // arithmetic sequence, so their byte-wise differences at the value's width are constant.
  uint32_t delta = 0;
  // With data == nullptr: writes bytes [begin, begin + n) of the array to `out`. The derived
  // arrays (flag bits as bytes, cell offsets and types, 5 bytes per cell) are never made whole
  // (issue 30: the write stage's memory).
  std::function<void(uint64_t begin, uint64_t n, uint8_t* out)> fill = nullptr;
};

// Bytes [begin, begin + n) of `a`: its own, or made into `scratch` (at least n bytes).
const uint8_t* ArrayBytes(const VtuArray& a, uint64_t begin, uint64_t n, uint8_t* scratch) {
  if (a.data != nullptr) return a.data + begin;
  a.fill(begin, n, scratch);
  return scratch;
}

// One vtkLZMADataCompressor block: an .xz stream (CRC64, as VTK's own compressor writes) of
// [delta filter,] LZMA2 at `preset`, with literal/position contexts aligned to the element
// size for multi-byte arrays. Encoded into `scratch` (grown to the bound), then copied to `out` at
// its size.
bool LzmaBlock(const uint8_t* in, size_t n, const VtuArray& a, int preset,
               std::vector<uint8_t>& scratch, std::vector<uint8_t>& out) {
  lzma_options_lzma opt;
  if (lzma_lzma_preset(&opt, static_cast<uint32_t>(preset))) return false;
  // xz's own modes: presets 1-3 are its fast mode, 4-9 normal mode (optimal parsing), which
  // makes the CT head's file at 50 % 16 % smaller but takes ~3x the time to write
  // (core/mesh/README.md "Compact meshes"); the default level 1 is the fast one.
  const size_t elem = std::strcmp(a.type, "UInt8") == 0 ? 1 : 4;
  if (elem == 4) {
    opt.lc = 0;
    opt.lp = 2;
    opt.pb = 2;
  }
  lzma_options_delta delta{};
  delta.type = LZMA_DELTA_TYPE_BYTE;
  delta.dist = a.delta;
  std::array<lzma_filter, 3> filters{};
  size_t f = 0;
  if (a.delta != 0) filters[f++] = {LZMA_FILTER_DELTA, &delta};
  filters[f++] = {LZMA_FILTER_LZMA2, &opt};
  filters[f] = {LZMA_VLI_UNKNOWN, nullptr};
  if (scratch.size() < lzma_stream_buffer_bound(n)) scratch.resize(lzma_stream_buffer_bound(n));
  size_t out_pos = 0;
  if (lzma_stream_buffer_encode(filters.data(), LZMA_CHECK_CRC64, nullptr, in, n, scratch.data(),
                                &out_pos, scratch.size()) != LZMA_OK)
    return false;
  out.assign(scratch.data(), scratch.data() + out_pos);
  return true;
}

// How one array is stored in the appended block: header, then payload (compressed blocks or
// the array's bytes), starting at `offset` bytes after the '_' marker.
struct EncodedArray {
  std::vector<uint8_t> header;
  std::vector<std::vector<uint8_t>> compressed_blocks;
  uint64_t offset = 0;
};

// Compresses every array into blocks of options.compressor, blocks spread over threads. Each block
// is encoded into a scratch buffer of its bound and kept at its compressed size: a vector sized to
// the bound and shrunk with resize kept its whole capacity, zero-filled, so the blocks held as
// many resident bytes as the arrays themselves (issue 30).
absl::Status CompressArrays(const std::vector<VtuArray>& arrays, std::vector<EncodedArray>& enc,
                            const VtuWriteOptions& options, const std::filesystem::path& path) {
  struct Task {
    const VtuArray* array;
    EncodedArray* out;
    uint64_t block;
  };
  std::vector<Task> tasks;
  for (size_t i = 0; i < arrays.size(); ++i) {
    const uint64_t nblocks = (arrays[i].bytes + kVtuBlockBytes - 1) / kVtuBlockBytes;
    enc[i].compressed_blocks.resize(nblocks);
    for (uint64_t b = 0; b < nblocks; ++b) tasks.push_back({&arrays[i], &enc[i], b});
  }
  // Blocks are 1 MiB but the last of each array, so contiguous ranges balance well; each block
  // is compressed alone, so the bytes do not depend on the thread count.
  std::atomic<bool> failed{false};
  ParallelFor(static_cast<int64_t>(tasks.size()), ResolveThreads(options.threads),
              [&](int64_t first, int64_t last) {
                std::vector<uint8_t> made(kVtuBlockBytes), scratch;
                for (int64_t i = first; i < last && !failed; ++i) {
                  const Task& t = tasks[i];
                  const uint64_t begin = t.block * kVtuBlockBytes;
                  const uint64_t n = std::min(kVtuBlockBytes, t.array->bytes - begin);
                  const uint8_t* in = ArrayBytes(*t.array, begin, n, made.data());
                  std::vector<uint8_t>& out = t.out->compressed_blocks[t.block];
                  if (options.compressor == VtuCompressor::kLzma) {
                    if (!LzmaBlock(in, n, *t.array, options.level, scratch, out)) {
                      failed = true;
                      return;
                    }
                    continue;
                  }
                  uLongf out_len = compressBound(static_cast<uLong>(n));
                  if (scratch.size() < out_len) scratch.resize(out_len);
                  if (compress2(scratch.data(), &out_len, in, static_cast<uLong>(n),
                                options.level) != Z_OK) {
                    failed = true;
                    return;
                  }
                  out.assign(scratch.data(), scratch.data() + out_len);
                }
              });
  if (failed)
    return absl::InternalError(absl::StrCat(
        PathString(path), ": ", options.compressor == VtuCompressor::kLzma ? "LZMA" : "zlib",
        " compression failed"));

  for (size_t i = 0; i < arrays.size(); ++i) {
    EncodedArray& e = enc[i];
    const uint64_t nblocks = e.compressed_blocks.size();
    std::vector<uint64_t> h = {nblocks, kVtuBlockBytes, arrays[i].bytes % kVtuBlockBytes};
    for (const auto& b : e.compressed_blocks) h.push_back(b.size());
    e.header.assign(Bytes(h), Bytes(h) + h.size() * sizeof(uint64_t));
  }
  return absl::OkStatus();
}

}  // namespace

namespace {

// The region table as VTK field data, inline ASCII (a few bytes; the appended block stays the
// mesh's). A String array in VTK's ASCII form is each string's bytes as numbers, each string
// ended by a 0 (vtkXMLWriter's encoding), so names need no XML escaping.
std::string RegionFieldData(const RegionTable* table) {
  if (table == nullptr || table->regions.empty()) return "";
  const size_t n = table->regions.size();
  std::string names, labels, colours;
  for (const RegionInfo& r : table->regions) {
    for (char c : r.name) absl::StrAppend(&names, int{static_cast<unsigned char>(c)}, " ");
    absl::StrAppend(&names, "0 ");
    absl::StrAppend(&labels, int{r.label}, " ");
    absl::StrAppend(&colours, int{r.rgb[0]}, " ", int{r.rgb[1]}, " ", int{r.rgb[2]}, " ");
  }
  return absl::StrCat(
      "    <FieldData>\n      <Array type=\"String\" Name=\"region_names\" NumberOfTuples=\"", n,
      "\" format=\"ascii\">\n        ", names,
      "\n      </Array>\n      <DataArray type=\"UInt8\" Name=\"region_labels\" "
      "NumberOfTuples=\"",
      n, "\" format=\"ascii\">\n        ", labels,
      "\n      </DataArray>\n      <DataArray type=\"UInt8\" Name=\"region_colors\" "
      "NumberOfComponents=\"3\" NumberOfTuples=\"",
      n, "\" format=\"ascii\">\n        ", colours, "\n      </DataArray>\n    </FieldData>\n");
}

}  // namespace

const char* VtuCompressorName(VtuCompressor compressor) {
  return compressor == VtuCompressor::kLzma ? "lzma" : "zlib";
}

std::optional<VtuCompressor> ParseVtuCompressor(std::string_view name) {
  if (name == "zlib") return VtuCompressor::kZlib;
  if (name == "lzma") return VtuCompressor::kLzma;
  return std::nullopt;
}

absl::Status WriteVtu(const TetMesh& mesh, const std::filesystem::path& path,
                      const VtuWriteOptions& options) {
  DECIMA_RETURN_IF_ERROR(CheckMeshForWriting(mesh, path));
  if (options.compress && (options.level < 1 || options.level > 9))
    return absl::InvalidArgumentError(absl::StrCat("cannot write ", PathString(path),
                                                   ": compression level ", options.level,
                                                   " is outside 1..9"));
  const int64_t nv = mesh.vertex_count(), nt = mesh.tet_count();

  // Derived arrays, made a block at a time (VtuArray::fill): flag bits as 0/1 bytes, offsets and
  // cell types.
  auto flag_bytes = [&mesh](uint8_t bit) {
    return [&mesh, bit](uint64_t begin, uint64_t n, uint8_t* out) {
      for (uint64_t i = 0; i < n; ++i) out[i] = (mesh.vertex_flags[begin + i] & bit) ? 1 : 0;
    };
  };
  // Cell t ends at 4 (t + 1); `width` bytes per offset, the byte range whole offsets (blocks are
  // a multiple of 8 bytes).
  auto offsets = [](uint64_t width) {
    return [width](uint64_t begin, uint64_t n, uint8_t* out) {
      for (uint64_t b = 0; b < n; b += width) {
        const int64_t end = 4 * (int64_t((begin + b) / width) + 1);
        if (width == 8) {
          std::memcpy(out + b, &end, 8);
        } else {
          const int32_t end32 = static_cast<int32_t>(end);
          std::memcpy(out + b, &end32, 4);
        }
      }
    };
  };
  const bool offsets64 = 4 * nt > std::numeric_limits<int32_t>::max();
  std::vector<VtuArray> arrays = {
      {"PointData", "Float32", "scalar", 1, Bytes(mesh.scalars), 4 * uint64_t(nv)},
      {"PointData", "UInt8", "label", 1, Bytes(mesh.labels), uint64_t(nv)},
      {"PointData", "UInt8", "feature", 1, nullptr, uint64_t(nv), 0, flag_bytes(kFeatureVertex)},
      {"PointData", "Float32", "interface_distance", 1, Bytes(mesh.interface_distance),
       4 * uint64_t(nv)},
      {"PointData", "UInt8", "boundary", 1, nullptr, uint64_t(nv), 0,
       flag_bytes(kExteriorBoundaryVertex)},
      {"CellData", "UInt8", "region", 1, Bytes(mesh.cell_regions), uint64_t(nt)},
      {"Points", "Float32", "Points", 3, Bytes(mesh.positions), 12 * uint64_t(nv)},
      {"Cells", "Int32", "connectivity", 1, Bytes(mesh.tets), 16 * uint64_t(nt)},
      offsets64
          ? VtuArray{"Cells", "Int64", "offsets", 1, nullptr, 8 * uint64_t(nt), 8, offsets(8)}
          : VtuArray{"Cells", "Int32", "offsets", 1, nullptr, 4 * uint64_t(nt), 4, offsets(4)},
      {"Cells", "UInt8", "types", 1, nullptr, uint64_t(nt), 0,
       [](uint64_t, uint64_t n, uint8_t* out) { std::memset(out, kVtkTetra, n); }},
  };

  std::vector<EncodedArray> enc(arrays.size());
  if (options.compress) {
    DECIMA_RETURN_IF_ERROR(CompressArrays(arrays, enc, options, path));
  } else {
    for (size_t i = 0; i < arrays.size(); ++i) {
      const uint64_t n = arrays[i].bytes;
      enc[i].header.assign(reinterpret_cast<const uint8_t*>(&n),
                           reinterpret_cast<const uint8_t*>(&n) + sizeof(n));
    }
  }
  uint64_t offset = 0;
  for (size_t i = 0; i < arrays.size(); ++i) {
    enc[i].offset = offset;
    offset += enc[i].header.size();
    if (options.compress) {
      for (const auto& b : enc[i].compressed_blocks) offset += b.size();
    } else {
      offset += arrays[i].bytes;
    }
  }

  std::string xml = absl::StrCat(
      "<?xml version=\"1.0\"?>\n"
      "<VTKFile type=\"UnstructuredGrid\" version=\"1.0\" byte_order=\"LittleEndian\" "
      "header_type=\"UInt64\"",
      !options.compress                            ? ""
      : options.compressor == VtuCompressor::kLzma ? " compressor=\"vtkLZMADataCompressor\""
                                                   : " compressor=\"vtkZLibDataCompressor\"",
      ">\n  <UnstructuredGrid>\n", RegionFieldData(options.regions), "    <Piece NumberOfPoints=\"",
      nv, "\" NumberOfCells=\"", nt, "\">\n");
  const char* open_section = nullptr;
  for (size_t i = 0; i < arrays.size(); ++i) {
    const VtuArray& a = arrays[i];
    if (open_section == nullptr || std::strcmp(open_section, a.section) != 0) {
      if (open_section != nullptr) absl::StrAppend(&xml, "      </", open_section, ">\n");
      open_section = a.section;
      absl::StrAppend(&xml, "      <", a.section);
      if (std::strcmp(a.section, "PointData") == 0) absl::StrAppend(&xml, " Scalars=\"scalar\"");
      if (std::strcmp(a.section, "CellData") == 0) absl::StrAppend(&xml, " Scalars=\"region\"");
      absl::StrAppend(&xml, ">\n");
    }
    absl::StrAppend(&xml, "        <DataArray type=\"", a.type, "\" Name=\"", a.name, "\"");
    if (a.components != 1) absl::StrAppend(&xml, " NumberOfComponents=\"", a.components, "\"");
    absl::StrAppend(&xml, " format=\"appended\" offset=\"", enc[i].offset, "\"/>\n");
  }
  absl::StrAppend(&xml, "      </", open_section, ">\n    </Piece>\n  </UnstructuredGrid>\n",
                  "  <AppendedData encoding=\"raw\">\n   _");

  AtomicFile file;
  DECIMA_RETURN_IF_ERROR(file.Open(path));
  DECIMA_RETURN_IF_ERROR(file.Write(xml));
  std::vector<uint8_t> made;  // a block of a derived array, uncompressed
  for (size_t i = 0; i < arrays.size(); ++i) {
    DECIMA_RETURN_IF_ERROR(file.Write(enc[i].header.data(), enc[i].header.size()));
    if (options.compress) {
      for (const auto& b : enc[i].compressed_blocks)
        DECIMA_RETURN_IF_ERROR(file.Write(b.data(), b.size()));
    } else if (arrays[i].data != nullptr) {
      DECIMA_RETURN_IF_ERROR(file.Write(arrays[i].data, arrays[i].bytes));
    } else {
      if (made.empty()) made.resize(kVtuBlockBytes);
      for (uint64_t begin = 0; begin < arrays[i].bytes; begin += kVtuBlockBytes) {
        const uint64_t n = std::min(kVtuBlockBytes, arrays[i].bytes - begin);
        DECIMA_RETURN_IF_ERROR(file.Write(ArrayBytes(arrays[i], begin, n, made.data()), n));
      }
    }
  }
  DECIMA_RETURN_IF_ERROR(file.Write("\n  </AppendedData>\n</VTKFile>\n"));
  return file.Commit();
}

// ---------------------------------------------------------------------------------------------
// Gmsh .msh 4.1

namespace {

struct RegionGroups {
  std::vector<int> regions;                 // regions present, increasing
  std::vector<std::vector<int64_t>> tets;   // per entry of `regions`: tet ids, increasing
  std::vector<std::array<double, 6>> bbox;  // per entry: min xyz, max xyz
  std::vector<std::string> names;           // per entry: the physical group's name
};

RegionGroups GroupByRegion(const TetMesh& mesh) {
  const int64_t nt = mesh.tet_count();
  std::array<int64_t, 256> count{};
  for (int64_t t = 0; t < nt; ++t) ++count[mesh.cell_regions[t]];
  RegionGroups g;
  std::array<int, 256> slot;
  slot.fill(-1);
  for (int r = 0; r < 256; ++r) {
    if (count[r] == 0) continue;
    slot[r] = static_cast<int>(g.regions.size());
    g.regions.push_back(r);
    g.tets.emplace_back().reserve(count[r]);
  }
  // A mesh without tets still needs one entity to hold its nodes.
  if (g.regions.empty()) {
    g.regions.push_back(0);
    g.tets.emplace_back();
  }
  for (int64_t t = 0; t < nt; ++t) g.tets[slot[mesh.cell_regions[t]]].push_back(t);
  const double inf = std::numeric_limits<double>::infinity();
  g.bbox.assign(g.regions.size(), {inf, inf, inf, -inf, -inf, -inf});
  for (size_t e = 0; e < g.regions.size(); ++e) {
    auto& b = g.bbox[e];
    for (int64_t t : g.tets[e]) {
      for (int q = 0; q < 4; ++q) {
        const float* p = &mesh.positions[3 * mesh.tets[4 * t + q]];
        for (int c = 0; c < 3; ++c) {
          b[c] = std::min<double>(b[c], p[c]);
          b[3 + c] = std::max<double>(b[3 + c], p[c]);
        }
      }
    }
    if (g.tets[e].empty()) {  // node-only entity: the box of all vertices
      for (int64_t v = 0; v < mesh.vertex_count(); ++v) {
        for (int c = 0; c < 3; ++c) {
          b[c] = std::min<double>(b[c], mesh.positions[3 * v + c]);
          b[3 + c] = std::max<double>(b[3 + c], mesh.positions[3 * v + c]);
        }
      }
      if (mesh.vertex_count() == 0) b = {0, 0, 0, 0, 0, 0};
    }
  }
  return g;
}

// $PhysicalNames (ASCII in both variants): region r is the volume group r + 1, named as the
// region table says (or "region_<r>" without one).
std::string PhysicalNames(const RegionGroups& g) {
  std::string s = absl::StrCat("$PhysicalNames\n", g.regions.size(), "\n");
  for (size_t e = 0; e < g.regions.size(); ++e) {
    absl::StrAppend(&s, "3 ", g.regions[e] + 1, " \"", g.names[e], "\"\n");
  }
  return s + "$EndPhysicalNames\n";
}

// A region's physical name: the table's, with what would end Gmsh's quoted string or line
// (double quote, line breaks; the table's rule already refuses control characters) replaced.
std::string PhysicalName(int region, const RegionTable* table) {
  if (table == nullptr || static_cast<size_t>(region) >= table->regions.size()) {
    return absl::StrCat("region_", region);
  }
  std::string n = table->regions[region].name;
  for (char& c : n) {
    if (c == '"') c = '\'';
    if (c == '\n' || c == '\r') c = ' ';
  }
  return n;
}

// Appends the binary representation of `v` to `out`.
template <typename T>
void Put(std::string& out, T v) {
  out.append(reinterpret_cast<const char*>(&v), sizeof(T));
}

absl::Status WriteGmshBinary(const TetMesh& mesh, const RegionGroups& g, AtomicFile& file) {
  const uint64_t nv = mesh.vertex_count(), nt = mesh.tet_count();
  const size_t ne = g.regions.size();
  std::string s = "$MeshFormat\n4.1 1 8\n";
  Put<int32_t>(s, 1);  // lets the reader detect the byte order
  s += "\n$EndMeshFormat\n" + PhysicalNames(g) + "$Entities\n";
  Put<uint64_t>(s, 0);
  Put<uint64_t>(s, 0);
  Put<uint64_t>(s, 0);
  Put<uint64_t>(s, ne);
  for (size_t e = 0; e < ne; ++e) {
    Put<int32_t>(s, g.regions[e] + 1);
    for (double c : g.bbox[e]) Put<double>(s, c);
    Put<uint64_t>(s, 1);
    Put<int32_t>(s, g.regions[e] + 1);
    Put<uint64_t>(s, 0);  // no bounding surfaces: a discrete volume
  }
  s += "\n$EndEntities\n$Nodes\n";
  Put<uint64_t>(s, 1);
  Put<uint64_t>(s, nv);
  Put<uint64_t>(s, nv == 0 ? 0 : 1);
  Put<uint64_t>(s, nv);
  Put<int32_t>(s, 3);
  Put<int32_t>(s, g.regions[0] + 1);
  Put<int32_t>(s, 0);
  Put<uint64_t>(s, nv);
  DECIMA_RETURN_IF_ERROR(file.Write(s));

  // Node tags, then coordinates, each in chunks through one buffer.
  constexpr size_t kChunk = size_t{1} << 16;
  std::vector<uint64_t> tags(5 * kChunk);
  for (uint64_t begin = 0; begin < nv; begin += tags.size()) {
    const uint64_t n = std::min<uint64_t>(tags.size(), nv - begin);
    for (uint64_t i = 0; i < n; ++i) tags[i] = begin + i + 1;
    DECIMA_RETURN_IF_ERROR(file.Write(tags.data(), n * sizeof(uint64_t)));
  }
  std::vector<double> xyz(3 * kChunk);
  for (uint64_t begin = 0; begin < nv; begin += kChunk) {
    const uint64_t n = std::min<uint64_t>(kChunk, nv - begin);
    for (uint64_t i = 0; i < 3 * n; ++i) xyz[i] = mesh.positions[3 * begin + i];
    DECIMA_RETURN_IF_ERROR(file.Write(xyz.data(), 3 * n * sizeof(double)));
  }

  s = "\n$EndNodes\n$Elements\n";
  size_t blocks = 0;
  for (size_t e = 0; e < ne; ++e) blocks += g.tets[e].empty() ? 0 : 1;
  Put<uint64_t>(s, blocks);
  Put<uint64_t>(s, nt);
  Put<uint64_t>(s, nt == 0 ? 0 : 1);
  Put<uint64_t>(s, nt);
  DECIMA_RETURN_IF_ERROR(file.Write(s));
  for (size_t e = 0; e < ne; ++e) {
    const std::vector<int64_t>& ids = g.tets[e];
    if (ids.empty()) continue;
    s.clear();
    Put<int32_t>(s, 3);
    Put<int32_t>(s, g.regions[e] + 1);
    Put<int32_t>(s, 4);  // 4-node tetrahedron
    Put<uint64_t>(s, ids.size());
    DECIMA_RETURN_IF_ERROR(file.Write(s));
    // (tag, 4 node tags) per element.
    for (size_t begin = 0; begin < ids.size(); begin += tags.size() / 5) {
      const size_t n = std::min(tags.size() / 5, ids.size() - begin);
      for (size_t i = 0; i < n; ++i) {
        const int64_t t = ids[begin + i];
        uint64_t* o = &tags[5 * i];
        o[0] = t + 1;
        for (int q = 0; q < 4; ++q) o[1 + q] = uint64_t(mesh.tets[4 * t + q]) + 1;
      }
      DECIMA_RETURN_IF_ERROR(file.Write(tags.data(), 5 * n * sizeof(uint64_t)));
    }
  }
  return file.Write("\n$EndElements\n");
}

absl::Status WriteGmshAscii(const TetMesh& mesh, const RegionGroups& g, AtomicFile& file) {
  const uint64_t nv = mesh.vertex_count(), nt = mesh.tet_count();
  const size_t ne = g.regions.size();
  TextWriter w(&file);
  DECIMA_RETURN_IF_ERROR(w.Str("$MeshFormat\n4.1 0 8\n$EndMeshFormat\n"));
  DECIMA_RETURN_IF_ERROR(w.Str(PhysicalNames(g)));
  DECIMA_RETURN_IF_ERROR(w.Str("$Entities\n0 0 0 "));
  DECIMA_RETURN_IF_ERROR(w.Number(ne, '\n'));
  for (size_t e = 0; e < ne; ++e) {
    DECIMA_RETURN_IF_ERROR(w.Number(g.regions[e] + 1, ' '));
    for (double c : g.bbox[e]) DECIMA_RETURN_IF_ERROR(w.Number(c, ' '));
    DECIMA_RETURN_IF_ERROR(w.Str("1 "));
    DECIMA_RETURN_IF_ERROR(w.Number(g.regions[e] + 1, ' '));
    DECIMA_RETURN_IF_ERROR(w.Str("0\n"));
  }
  DECIMA_RETURN_IF_ERROR(w.Str("$EndEntities\n$Nodes\n1 "));
  DECIMA_RETURN_IF_ERROR(w.Number(nv, ' '));
  DECIMA_RETURN_IF_ERROR(w.Number(nv == 0 ? 0 : 1, ' '));
  DECIMA_RETURN_IF_ERROR(w.Number(nv, '\n'));
  DECIMA_RETURN_IF_ERROR(w.Str("3 "));
  DECIMA_RETURN_IF_ERROR(w.Number(g.regions[0] + 1, ' '));
  DECIMA_RETURN_IF_ERROR(w.Str("0 "));
  DECIMA_RETURN_IF_ERROR(w.Number(nv, '\n'));
  for (uint64_t v = 0; v < nv; ++v) DECIMA_RETURN_IF_ERROR(w.Number(v + 1, '\n'));
  for (uint64_t v = 0; v < nv; ++v) {
    DECIMA_RETURN_IF_ERROR(w.Number(mesh.positions[3 * v], ' '));
    DECIMA_RETURN_IF_ERROR(w.Number(mesh.positions[3 * v + 1], ' '));
    DECIMA_RETURN_IF_ERROR(w.Number(mesh.positions[3 * v + 2], '\n'));
  }
  size_t blocks = 0;
  for (size_t e = 0; e < ne; ++e) blocks += g.tets[e].empty() ? 0 : 1;
  DECIMA_RETURN_IF_ERROR(w.Str("$EndNodes\n$Elements\n"));
  DECIMA_RETURN_IF_ERROR(w.Number(blocks, ' '));
  DECIMA_RETURN_IF_ERROR(w.Number(nt, ' '));
  DECIMA_RETURN_IF_ERROR(w.Number(nt == 0 ? 0 : 1, ' '));
  DECIMA_RETURN_IF_ERROR(w.Number(nt, '\n'));
  for (size_t e = 0; e < ne; ++e) {
    if (g.tets[e].empty()) continue;
    DECIMA_RETURN_IF_ERROR(w.Str("3 "));
    DECIMA_RETURN_IF_ERROR(w.Number(g.regions[e] + 1, ' '));
    DECIMA_RETURN_IF_ERROR(w.Str("4 "));
    DECIMA_RETURN_IF_ERROR(w.Number(g.tets[e].size(), '\n'));
    for (int64_t t : g.tets[e]) {
      DECIMA_RETURN_IF_ERROR(w.Number(t + 1, ' '));
      for (int q = 0; q < 4; ++q)
        DECIMA_RETURN_IF_ERROR(w.Number(int64_t(mesh.tets[4 * t + q]) + 1, q == 3 ? '\n' : ' '));
    }
  }
  DECIMA_RETURN_IF_ERROR(w.Str("$EndElements\n"));
  return w.Flush();
}

}  // namespace

absl::Status WriteGmsh(const TetMesh& mesh, const std::filesystem::path& path,
                       const GmshWriteOptions& options) {
  DECIMA_RETURN_IF_ERROR(CheckMeshForWriting(mesh, path));
  RegionGroups g = GroupByRegion(mesh);
  for (int r : g.regions) g.names.push_back(PhysicalName(r, options.regions));
  AtomicFile file;
  DECIMA_RETURN_IF_ERROR(file.Open(path));
  if (options.binary) {
    DECIMA_RETURN_IF_ERROR(WriteGmshBinary(mesh, g, file));
  } else {
    DECIMA_RETURN_IF_ERROR(WriteGmshAscii(mesh, g, file));
  }
  return file.Commit();
}

// ---------------------------------------------------------------------------------------------
// MEDIT .mesh

absl::Status WriteMedit(const TetMesh& mesh, const std::filesystem::path& path) {
  DECIMA_RETURN_IF_ERROR(CheckMeshForWriting(mesh, path));
  const int64_t nv = mesh.vertex_count(), nt = mesh.tet_count();
  AtomicFile file;
  DECIMA_RETURN_IF_ERROR(file.Open(path));
  TextWriter w(&file);
  DECIMA_RETURN_IF_ERROR(w.Str("MeshVersionFormatted 2\n\nDimension 3\n\nVertices\n"));
  DECIMA_RETURN_IF_ERROR(w.Number(nv, '\n'));
  for (int64_t v = 0; v < nv; ++v) {
    for (int c = 0; c < 3; ++c) DECIMA_RETURN_IF_ERROR(w.Number(mesh.positions[3 * v + c], ' '));
    DECIMA_RETURN_IF_ERROR(w.Number(int(mesh.labels[v]), '\n'));
  }
  DECIMA_RETURN_IF_ERROR(w.Str("\nTetrahedra\n"));
  DECIMA_RETURN_IF_ERROR(w.Number(nt, '\n'));
  for (int64_t t = 0; t < nt; ++t) {
    for (int q = 0; q < 4; ++q)
      DECIMA_RETURN_IF_ERROR(w.Number(int64_t(mesh.tets[4 * t + q]) + 1, ' '));
    DECIMA_RETURN_IF_ERROR(w.Number(int(mesh.cell_regions[t]) + 1, '\n'));
  }
  DECIMA_RETURN_IF_ERROR(w.Str("\nEnd\n"));
  DECIMA_RETURN_IF_ERROR(w.Flush());
  return file.Commit();
}

absl::Status WriteMesh(const TetMesh& mesh, const std::filesystem::path& path) {
  const std::string ext = path.extension().string();
  if (ext == ".vtu") return WriteVtu(mesh, path);
  if (ext == ".msh") return WriteGmsh(mesh, path);
  if (ext == ".mesh") return WriteMedit(mesh, path);
  return absl::InvalidArgumentError(absl::StrCat("cannot write ", PathString(path),
                                                 ": unknown mesh extension '", ext,
                                                 "' (expected .vtu, .msh or .mesh)"));
}

}  // namespace decima
