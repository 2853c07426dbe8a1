// The level record on disk: `mesh.levels`, a little-endian binary sidecar beside the job's mesh
// (format in core/simplify/README.md, "The .levels file"). Its reader is a reader of outside
// data: every count is checked against the file's size before anything is allocated, and what it
// returns has passed ValidateLevels.
#pragma once

#include <cstdint>
#include <filesystem>
#include <string>
#include <string_view>

#include "absl/status/statusor.h"
#include "core/mesh/tet_mesh.h"
#include "core/simplify/simplify.h"

namespace decima {

inline constexpr char kLevelsMagic[8] = {'D', 'E', 'C', 'I', 'M', 'A', 'L', 'V'};
inline constexpr uint32_t kLevelsVersion = 1;

// A 64-bit digest of what a level's mesh is made of (positions, values, labels, interface
// distances, flags, cells), so that a record is only ever applied to the mesh it was made on
// (the base mesh is rebuilt from the volume and the segmentation, not stored).
uint64_t BaseMeshDigest(const TetMesh& mesh);

// The checksum a file ends with: of every byte before it.
uint64_t LevelsChecksum(std::string_view bytes_before_checksum);

// The file's bytes for `levels` (zlib level `compression`, 1..9).
std::string SerializeLevels(const SimplifyLevels& levels, int compression = 6);
// The record in `bytes`, or InvalidArgument naming `name` and what is wrong (bad magic, a
// version this reader does not know, a count that does not fit the file, a bad checksum, a
// payload that does not inflate to its counts, collapses that are no simplicial map).
absl::StatusOr<SimplifyLevels> ParseLevels(std::string_view bytes,
                                           std::string_view name = "levels");

// Written under a temporary name and renamed, as the mesh writers do.
absl::Status WriteLevels(const SimplifyLevels& levels, const std::filesystem::path& path);
absl::StatusOr<SimplifyLevels> ReadLevels(const std::filesystem::path& path);

}  // namespace decima
