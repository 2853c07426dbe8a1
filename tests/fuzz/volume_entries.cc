// Fuzz entries of the volume readers (NIfTI, MetaImage, NRRD) and of the DICOM reader (the
// structural preflight, then GDCM through ListDicomSeries and ReadDicomSeries).
#include <unistd.h>

#include <cstdio>
#include <filesystem>
#include <string>
#include <string_view>
#include <vector>

#include "core/io/dicom.h"
#include "core/io/dicom_preflight.h"
#include "core/io/volume_io.h"
#include "core/volume/volume.h"
#include "tests/fuzz/fuzz_entries.h"
#include "tests/fuzz/fuzz_require.h"

namespace decima::fuzz {
namespace {

namespace fs = std::filesystem;

// A fresh, empty folder of this process (parallel fuzzing jobs do not share it).
fs::path ScratchDir(const char* what) {
  const fs::path dir = fs::temp_directory_path() /
                       (std::string("decima-") + what + "-fuzz-" + std::to_string(::getpid()));
  std::error_code ec;
  fs::remove_all(dir, ec);
  fs::create_directories(dir, ec);
  return dir;
}

void WriteFile(const fs::path& path, std::string_view bytes) {
  if (std::FILE* f = std::fopen(path.c_str(), "wb")) {
    if (!bytes.empty()) std::fwrite(bytes.data(), 1, bytes.size(), f);
    std::fclose(f);
  }
}

// The input split at every kFileSeparator: the first part is the header file, the others the
// detached data files (or further DICOM slices). Seeds mark the split with the same string, so
// the fuzzer can keep or move it.
std::vector<std::string_view> SplitFiles(const uint8_t* data, size_t size) {
  std::string_view in(reinterpret_cast<const char*>(data), size);
  std::vector<std::string_view> parts;
  for (;;) {
    const size_t at = in.find(kFileSeparator);
    if (at == std::string_view::npos || parts.size() == 7) break;
    parts.push_back(in.substr(0, at));
    in.remove_prefix(at + kFileSeparator.size());
  }
  parts.push_back(in);
  return parts;
}

// A volume a reader returned must pass Validate, and ProbeVolume (the server's header-only
// check) must have accepted the file with the same dimensions.
void CheckRead(const absl::StatusOr<Volume>& volume, const fs::path& path) {
  SetLastInputAccepted(volume.ok());
  if (!volume.ok()) {
    Require(!volume.status().message().empty(), "an error has a message");
    return;
  }
  Require(Validate(*volume, "fuzz").ok(), "a returned volume passes Validate");
  auto probe = io::ProbeVolume(path);
  Require(probe.ok(), "ProbeVolume accepts what the reader reads");
  Require(!probe->parsed || probe->dims == volume->dims, "ProbeVolume's dims are the reader's");
}

// Header file `name`, data files named by `data_names` (in order) in a fresh folder.
fs::path WriteVolumeFiles(const char* what, const uint8_t* data, size_t size, const char* name,
                          std::initializer_list<const char*> data_names) {
  const fs::path dir = ScratchDir(what);
  const auto parts = SplitFiles(data, size);
  WriteFile(dir / name, parts[0]);
  size_t i = 1;
  for (const char* d : data_names) {
    if (i < parts.size()) WriteFile(dir / d, parts[i++]);
  }
  return dir / name;
}

bool last_accepted = false;

}  // namespace

bool LastInputAccepted() { return last_accepted; }
void SetLastInputAccepted(bool accepted) { last_accepted = accepted; }

int NiftiEntry(const uint8_t* data, size_t size) {
  // First byte: single file (.nii) or a pair (.hdr + .img); gzip is detected by magic bytes.
  SetLastInputAccepted(false);
  if (size < 1) return 0;
  const bool pair = data[0] & 1;
  const fs::path path = pair ? WriteVolumeFiles("nifti", data + 1, size - 1, "v.hdr", {"v.img"})
                             : WriteVolumeFiles("nifti", data + 1, size - 1, "v.nii", {});
  CheckRead(io::ReadNifti(path), path);
  return 0;
}

int MetaImageEntry(const uint8_t* data, size_t size) {
  // First byte: .mha (data attached) or .mhd with detached files a.raw / a.zraw.
  SetLastInputAccepted(false);
  if (size < 1) return 0;
  const bool detached = data[0] & 1;
  const fs::path path =
      detached ? WriteVolumeFiles("metaimage", data + 1, size - 1, "v.mhd", {"a.raw", "a.zraw"})
               : WriteVolumeFiles("metaimage", data + 1, size - 1, "v.mha", {});
  CheckRead(io::ReadMetaImage(path), path);
  return 0;
}

int NrrdEntry(const uint8_t* data, size_t size) {
  // First byte: .nrrd (data attached) or .nhdr with detached files a.raw / a.raw.gz.
  SetLastInputAccepted(false);
  if (size < 1) return 0;
  const bool detached = data[0] & 1;
  const fs::path path =
      detached ? WriteVolumeFiles("nrrd", data + 1, size - 1, "v.nhdr", {"a.raw", "a.raw.gz"})
               : WriteVolumeFiles("nrrd", data + 1, size - 1, "v.nrrd", {});
  CheckRead(io::ReadNrrd(path), path);
  return 0;
}

int VolumeHeaderEntry(const uint8_t* data, size_t size) {
  SetLastInputAccepted(false);
  if (size < 1) return 0;
  const uint8_t* in = data + 1;
  const size_t n = size - 1;
  fs::path path;
  switch (data[0] % 6) {
    case 0:
      path = WriteVolumeFiles("header", in, n, "v.nii", {});
      break;
    case 1:
      path = WriteVolumeFiles("header", in, n, "v.hdr", {"v.img"});
      break;
    case 2:
      path = WriteVolumeFiles("header", in, n, "v.mha", {});
      break;
    case 3:
      path = WriteVolumeFiles("header", in, n, "v.mhd", {"a.raw", "a.zraw"});
      break;
    case 4:
      path = WriteVolumeFiles("header", in, n, "v.nrrd", {});
      break;
    default:
      path = WriteVolumeFiles("header", in, n, "v.nhdr", {"a.raw", "a.raw.gz"});
      break;
  }
  auto probe = io::ProbeVolume(path);
  if (!probe.ok()) {
    Require(
        probe.status().message().find(path.string()) != std::string_view::npos ||
            probe.status().message().find(path.parent_path().string()) != std::string_view::npos,
        "a refused header names its file");
    return 0;
  }
  SetLastInputAccepted(true);
  Require(probe->parsed, "a file's header is parsed (only a DICOM folder is not)");
  int64_t voxels = 1;
  for (int64_t d : probe->dims) {
    Require(d >= 1 && d <= kMaxVoxels, "each dim is in 1..kMaxVoxels");
    voxels *= d;  // each <= 2^31 and the running product <= 2^31: no overflow
    Require(voxels <= kMaxVoxels, "the voxel count is at most kMaxVoxels");
  }
  return 0;
}

int DicomEntry(const uint8_t* data, size_t size) {
  // Each part is one file of a series folder. The preflight must decide every part; the folder
  // then goes through the GDCM-backed listing and reader, which must not crash or abort.
  const auto parts = SplitFiles(data, size);
  const fs::path dir = ScratchDir("dicom");
  for (size_t i = 0; i < parts.size(); ++i) {
    (void)dicom_internal::CheckDicomStructure(absl::string_view(parts[i].data(), parts[i].size()));
    WriteFile(dir / ("IM" + std::to_string(i)), parts[i]);
  }
  auto series = ListDicomSeries(dir);
  auto volume = ReadDicomSeries(dir);
  SetLastInputAccepted(volume.ok());
  if (volume.ok()) {
    Require(Validate(*volume, "fuzz").ok(), "a returned volume passes Validate");
    Require(series.ok() && series->size() == 1, "a series that reads is listed, alone");
  }
  auto any = io::ReadVolume(dir);  // the dispatch the job's load stage uses
  Require(any.ok() == volume.ok(), "ReadVolume of the folder agrees with ReadDicomSeries");
  return 0;
}

}  // namespace decima::fuzz
