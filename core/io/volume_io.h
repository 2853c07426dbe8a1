// Volume file readers and writers: NIfTI-1/2, MetaImage (.mha/.mhd), NRRD (.nrrd/.nhdr).
//
// Contracts shared by every function here:
//  - Pure functions over values: no global state, safe to call from several threads at once
//    (on different output paths for the writers).
//  - A returned Volume passed Validate(): dims >= 2 along every axis, product <= kMaxVoxels,
//    finite positive spacing, orthonormal direction, no NaN/infinite voxels. Geometry is in LPS
//    millimetres (see core/volume/volume.h); RAS formats (NIfTI, NRRD "right-anterior-superior")
//    are converted by negating the first two rows of their index-to-world affine.
//  - Any problem with the file is an InvalidArgument (bad content), NotFound (missing file) or
//    Unimplemented (valid but unsupported feature) Status whose message starts with the file
//    path and names the field and what was expected. Header sizes are checked against
//    kMaxVoxels and against the bytes actually available BEFORE any voxel buffer is allocated;
//    compressed streams are never inflated beyond the header-implied size plus one byte.
//  - Writers go through a temporary file in the destination folder that is renamed into place
//    only when complete, so a failed write leaves no partial file under the target name.
//
// DICOM series (folders) are read by ReadDicomSeries() in core/io/dicom.h; ReadVolume() hands a
// directory to it (the folder must then hold exactly one series).
#pragma once

#include <array>
#include <cstdint>
#include <filesystem>
#include <string>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "core/volume/volume.h"

namespace decima::io {

// File formats ReadVolume() recognises.
enum class VolumeFormat { kUnknown, kNifti, kMetaImage, kNrrd, kDirectory };

// Format of `path`: by extension (.nii, .nii.gz, .hdr, .img, .mha, .mhd, .nrrd, .nhdr; case-
// insensitive), else by magic bytes (NIfTI header, optionally gzip-wrapped; "NRRD000"; MetaImage
// "ObjectType"/"NDims" key), kDirectory for a folder, kUnknown if nothing matches or the file
// cannot be opened.
VolumeFormat DetectVolumeFormat(const std::filesystem::path& path);

// Format of a file by its name alone: .nii, .nii.gz, .hdr, .img (optionally .gz), .mha, .mhd,
// .nrrd, .nhdr, case-insensitive; kUnknown otherwise. The one extension table of the project.
VolumeFormat VolumeFormatFromName(const std::filesystem::path& name);

// What a volume holds, from its header alone.
struct VolumeHeader {
  VolumeFormat format = VolumeFormat::kUnknown;
  std::filesystem::path input;  // what ReadVolume opens: the file, or the DICOM folder
  bool parsed = false;          // false for a DICOM folder: dims come from the full read
  std::array<int64_t, 3> dims{0, 0, 0};
  std::array<double, 3> spacing{0, 0, 0};  // mm
  std::string modality;                    // "CT", "MR", or "" when the format has none
  VoxelType type = VoxelType::kUInt8;      // the type ReadVolume returns (after any rescale)
};

// Reads the header of `path` (a file, or a folder of DICOM files) and checks that the data can
// be there, without reading a voxel: raw data must fill the file exactly, compressed data must
// fit zlib's maximum ratio, so time and memory stay small whatever the header claims (a
// decompression bomb is not inflated here). A folder: every regular file must carry the DICOM
// marker (HasDicomMarker); its geometry is left to ReadDicomSeries. Errors as ReadVolume's;
// a file ProbeVolume accepts can still fail ReadVolume on its voxels (NaN, corrupt stream).
absl::StatusOr<VolumeHeader> ProbeVolume(const std::filesystem::path& path);

// Reads any supported format (dispatch by DetectVolumeFormat). A directory is read as a DICOM
// series (ReadDicomSeries with no series uid: several series give InvalidArgument listing them);
// an unknown format yields InvalidArgument naming the extensions that are supported.
absl::StatusOr<Volume> ReadVolume(const std::filesystem::path& path);

// NIfTI-1 or NIfTI-2, single file (.nii, .nii.gz) or pair (.hdr + .img, either name may be
// given; each may be gzipped). Gzip is detected by magic bytes, not by extension. Geometry:
// sform if sform_code > 0 (direction = normalised columns), else qform if qform_code > 0, else
// pixdim only (identity direction in RAS, so LPS direction diag(-1, -1, 1)); spacing = |pixdim|.
// If scl_slope is finite, non-zero and (slope, inter) != (1, 0) voxels are rescaled to float32,
// otherwise the stored type is kept. Only 3D scalar data (dim[0] >= 3 and dim[4..7] == 1) of
// types uint8/int8/(u)int16/(u)int32/float32/float64. modality is "" (NIfTI carries none).
absl::StatusOr<Volume> ReadNifti(const std::filesystem::path& path);

// MetaImage: .mha (header and data in one file, ElementDataFile = LOCAL) or .mhd with a
// detached data file (raw, or zlib when CompressedData = True). TransformMatrix m0..m8 follows
// ITK: direction(r, c) = m[c * 3 + r] (the matrix is written axis by axis). MetaImage
// coordinates are already LPS. Detached data files must be relative paths inside the header's
// folder (no "..", not absolute) so a header cannot point the reader at arbitrary files.
absl::StatusOr<Volume> ReadMetaImage(const std::filesystem::path& path);

// NRRD: .nrrd (attached data) or .nhdr ("data file:" detached, same path rule as MetaImage);
// encodings raw, gzip and ascii; "space" LPS/RAS/LAS/scanner-xyz/3D-right-handed converted to
// LPS; "space directions" columns carry spacing; else "spacings" (default 1). dimension must be
// 3, or 4 with a size-1 first or last axis; non-scalar "kinds" are rejected.
absl::StatusOr<Volume> ReadNrrd(const std::filesystem::path& path);

// NIfTI-1 single file; gzip-compressed when the name ends in ".gz" (".nii.gz"), otherwise the
// extension must be ".nii". qform and sform (code 1, scanner) both encode direction, spacing
// and origin after LPS -> RAS conversion; a left-handed direction is stored with qfac = -1.
// Header fields are float32, so geometry round-trips to ~1e-7 relative, voxels exactly.
absl::Status WriteNifti(const Volume& volume, const std::filesystem::path& path);

struct MetaImageWriteOptions {
  // Compress the voxel data with zlib (CompressedData = True; .zraw for .mhd). Default true:
  // label maps shrink ~50x and the readers of ITK, VTK, 3D Slicer all accept it.
  bool compress = true;
  // zlib level 1 (fast) .. 9 (small). Default 6, zlib's own default.
  int compression_level = 6;
};

// MetaImage: ".mha" writes one file; ".mhd" writes the header plus "<stem>.raw" (or ".zraw"
// when compressed) beside it. Little-endian data, ITK-compatible header.
absl::Status WriteMetaImage(const Volume& volume, const std::filesystem::path& path,
                            const MetaImageWriteOptions& options = {});

}  // namespace decima::io
