// Mesh files: VTK XML UnstructuredGrid (.vtu, write and read), Gmsh 4.1 (.msh, write) and
// MEDIT (.mesh, write).
//
// Every writer writes to a temporary file beside the target and renames it over the target only
// after everything was written and flushed, so a reader never sees a half-written mesh and a
// failed write leaves no file behind. Errors are absl::Status values naming the path. The
// writers only read the mesh: several threads may write the same mesh to different paths.
//
// What the files hold (per vertex / per cell of the TetMesh):
//   .vtu   point data "scalar" (Float32), "label" (UInt8), "feature" (UInt8, 1 if kFeatureVertex),
//          "interface_distance" (Float32), "boundary" (UInt8, 1 if kExteriorBoundaryVertex);
//          cell data "region" (UInt8); points Float32; cells VTK_TETRA (10).
//          field data (with a region table) "region_names" (String), "region_labels" (UInt8)
//          and "region_colors" (UInt8 x 3, sRGB): row i names and colours region
//          region_labels[i] (ParaView: Information panel, spreadsheet view "Field Data").
//   .msh   nodes and tets; region r is volume entity r + 1 with physical tag r + 1 named as
//          the region table says ("region_<r>" without one), so Gmsh and FEM codes see the
//          regions as named physical groups.
//   .mesh  vertex reference = vertex label, tetrahedron reference = cell region + 1 (the same
//          number as the .msh physical tag; MEDIT readers commonly treat 0 as "no reference").
#pragma once

#include <cstdint>
#include <filesystem>
#include <optional>
#include <string>
#include <string_view>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "core/mesh/tet_mesh.h"
#include "core/volume/regions.h"

namespace decima {

// How the arrays of a .vtu are compressed. Both are VTK's own compressors (the file's
// `compressor` attribute), read by VTK/ParaView 9 and by ReadVtu.
enum class VtuCompressor {
  // vtkZLibDataCompressor: faster to write and to read than kLzma, 1.7x its bytes (README.md
  // "Compact meshes" has the figures).
  kZlib,
  // vtkLZMADataCompressor: each block is one .xz stream (liblzma), whose filter chain is stored
  // in the stream, so VTK's decoder (lzma_stream_buffer_decode) undoes any chain xz knows. Each
  // array gets the chain that suits it: the cell offsets (4, 8, 12, ...) go through xz's delta
  // filter first (every byte difference is then constant: 2.4 MB under zlib level 1 on the CT
  // head at 50 %, a few hundred bytes here), and 4-byte arrays use LZMA2 with lc=0, lp=2, pb=2
  // (literal and position contexts aligned to 4 bytes). 40 % fewer bytes than kZlib at level 1.
  kLzma,
};

// "zlib" | "lzma": the name a job spec uses (JobSpec::mesh_compression, metrics.json).
const char* VtuCompressorName(VtuCompressor compressor);
// The compressor of a name VtuCompressorName gives (case-sensitive); nullopt otherwise.
std::optional<VtuCompressor> ParseVtuCompressor(std::string_view name);

struct VtuWriteOptions {
  // Compress every array (blocks of 1 MiB) with `compressor`; false writes raw arrays (fastest
  // to write and read, about 8x the bytes of kLzma).
  bool compress = true;
  // zlib by default: LZMA halves the bytes but writes 5-20x slower and VTK reads it ~2x slower
  // (README.md "Compact meshes"); a job chooses with JobSpec::mesh_compression.
  VtuCompressor compressor = VtuCompressor::kZlib;
  // The compressor's level, 1..9: zlib's level, or the xz preset (1 = fastest in both; zlib 6
  // saves another ~5 % at ~8x the time).
  int level = 1;
  // Threads compressing blocks in parallel (0 = hardware concurrency). The file's bytes do not
  // depend on it.
  int threads = 0;
  // Names and colours of the regions, written as field data (top of this file); none if null.
  const RegionTable* regions = nullptr;
};

// Writes `mesh` as a VTK XML UnstructuredGrid file (version 1.0, little endian, header_type
// UInt64, one appended raw-binary block, connectivity Int32, offsets Int32 or Int64 when
// 4 * tet_count() does not fit Int32). Arrays are written as listed at the top of this file.
// Errors: InvalidArgument if the mesh's arrays have inconsistent sizes, a tet references a
// missing vertex or the level is out of range; file-system failures map errno to a code
// (NotFound for a missing directory, PermissionDenied, ResourceExhausted for a full disk,
// otherwise Internal) with a message naming the path. Thread-safe for distinct paths.
absl::Status WriteVtu(const TetMesh& mesh, const std::filesystem::path& path,
                      const VtuWriteOptions& options = {});

// What ReadVtu found in the file, so a caller can say which values came from the file and which
// are the documented defaults (nothing is made up silently).
struct VtuReadReport {
  std::string scalar_array;             // name of the point array read as TetMesh::scalars
  bool has_labels = false;              // "label" present; else every vertex label is 0
  bool has_interface_distance = false;  // else +infinity everywhere
  bool has_vertex_flags = false;        // "feature" or "boundary" present; else flags are 0
  bool has_regions = false;             // cell "region" present; else every cell region is 0
  int64_t inverted_or_flat_cells = 0;   // kept by VtuReadOptions::allow_inverted_cells
};

struct VtuReadOptions {
  // Keep cells with signed volume <= 0 instead of rejecting the file, and count them in
  // VtuReadReport. For measuring meshes other tools wrote (VTK's quadric decimation leaves flat
  // cells at high reductions): the result then breaks TetMesh's orientation invariant, so only
  // code that tolerates such cells (core/metrics counts them) may use it.
  bool allow_inverted_cells = false;
};

// Reads a .vtu holding one piece of tetrahedra: the files WriteVtu writes, and what VTK writes
// for such a grid (appended raw or base64, inline base64 "binary", "ascii"; uncompressed,
// vtkZLibDataCompressor or vtkLZMADataCompressor; header_type UInt32 or UInt64; any integer/float
// array types). The field (TetMesh::scalars) is, in this order: the point array the file names as
// its active scalars (<PointData Scalars="...">; VTK's filters write theirs as "scalars"), the
// array named "scalar", the only point array (which must have a Name: the report names the field's
// source). If none applies (no point array, or several and none marked), or the active scalars name
// a missing array, it is an InvalidArgument error naming the file and the arrays: the field is
// never defaulted. Point arrays "label", "interface_distance",
// "feature", "boundary" and cell array "region" are optional: missing ones read as 0
// (interface_distance: +infinity), and `report` (if not null) says which were present.
// vertex_flags is rebuilt from "feature" and "boundary" (so a WriteVtu -> ReadVtu round trip
// gives back identical arrays for meshes whose flags use only those two bits).
// Everything is validated before use: XML structure, counts against array lengths, sizes against
// the file size before allocating (also for compressed data), zlib stream integrity, cell types
// (only VTK_TETRA), offsets, connectivity indices in range and distinct, positive orientation
// (unless options.allow_inverted_cells), finite positions and scalars, labels and regions < 8.
// Errors: NotFound if the file does not exist, InvalidArgument for malformed content, Unimplemented
// for valid VTK features outside this subset (big endian, other compressors, several pieces);
// messages name the path and field.
absl::StatusOr<TetMesh> ReadVtu(const std::filesystem::path& path, VtuReadReport* report = nullptr,
                                const VtuReadOptions& options = {});

struct GmshWriteOptions {
  // Binary (the default: coordinates as exact doubles, faster to write than ASCII) or ASCII
  // (shortest round-trip decimals). Sizes are similar (README.md "Measured"): binary spends 8
  // bytes per tag as Gmsh's format demands, ASCII is short for grid coordinates.
  bool binary = true;
  // The physical groups' names; "region_<r>" if null.
  const RegionTable* regions = nullptr;
};

// Writes `mesh` as a Gmsh 4.1 .msh file: $PhysicalNames, $Entities (one volume entity per
// region present, with its bounding box and physical tag), $Nodes (one block holding all
// vertices, node tag = vertex index + 1, classified on the first region's volume entity),
// $Elements (one block of 4-node tets, type 4, per region; element tag = tet index + 1).
// Readable by Gmsh 4.8. Errors as WriteVtu.
absl::Status WriteGmsh(const TetMesh& mesh, const std::filesystem::path& path,
                       const GmshWriteOptions& options = {});

// Writes `mesh` as an ASCII MEDIT .mesh file (MeshVersionFormatted 2, Dimension 3, Vertices,
// Tetrahedra, End) with the references described at the top of this file. Coordinates are
// written with the shortest decimal form that reads back as the same float. Errors as WriteVtu.
absl::Status WriteMedit(const TetMesh& mesh, const std::filesystem::path& path);

// Picks the writer by the extension of `path`: .vtu (default VtuWriteOptions), .msh (binary),
// .mesh. Errors: InvalidArgument for any other extension.
absl::Status WriteMesh(const TetMesh& mesh, const std::filesystem::path& path);

}  // namespace decima
