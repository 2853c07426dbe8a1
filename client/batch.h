// Batch submission (`decima submit DIR1 DIR2 ...`, `decima submit --each FOLDER`): finding the
// studies in folders, one volume and one job each, and the batch's exit code. Depends on the
// proto library and DCMTK's dcmdata (to read a DICOM file's SeriesInstanceUID), never on core.
#pragma once

#include <filesystem>
#include <string>
#include <vector>

#include "client/client_lib.h"

namespace decima::client {

// One study of a batch: the files of one volume, which becomes one job.
struct Study {
  std::filesystem::path source;  // the argument (or --each entry) it was found in
  std::string label;         // for the table: "scans/a.nii.gz", "ct1 (series ...4711, 53 files)"
  std::string display_name;  // the volume's display name on the server
  // A volume file (its header data files are added at upload), or the folder below which a
  // DICOM series' files were found.
  std::filesystem::path input;
  std::string series_uid;        // DICOM: the series; "" when its files carry none
  std::vector<InputFile> files;  // DICOM: the series' files, names relative to `input`
  bool dicom() const { return !files.empty(); }
};

// .nii, .nii.gz, .mha, .mhd, .nrrd, .nhdr in any case: the single-file and header volume
// formats the server reads (a .raw or .zraw data file is not a study of its own).
bool IsVolumeFileName(const std::string& file_name);

// The SeriesInstanceUID of a DICOM Part 10 file, read by DCMTK up to group 0020 only (the pixel
// data is never loaded); "" when the file has none. False with *error naming the file when
// DCMTK cannot parse it.
bool ReadSeriesUid(const std::filesystem::path& file, std::string* uid, std::string* error);

// The studies in `source`: a file is one study; a folder is searched below (hidden entries
// skipped): each volume file is one study, and the DICOM files (DICM marker, not DICOMDIR) are
// grouped by SeriesInstanceUID into one study per series, sorted by UID. Other files are
// ignored. An empty result means the folder holds no volume (for the caller to report).
// False with *error when `source` does not exist, a DICOM file cannot be parsed, or the folder
// holds a symbolic link (refused by name, as `decima submit DIR` does, never followed).
bool FindStudies(const std::filesystem::path& source, std::vector<Study>* studies,
                 std::string* error);

// The sources of `--each FOLDER`: its subfolders and volume files (IsVolumeFileName; hidden
// entries skipped), sorted by name. False with *error when FOLDER is not a readable folder.
bool EachEntry(const std::filesystem::path& folder, std::vector<std::filesystem::path>* entries,
               std::string* error);

// A batch's exit code from each study's own (0, kJobFailed for a failed job or a study refused
// before its job existed, kJobCancelled, kTargetNotReached, ...): 0 only when every study
// succeeded; otherwise kJobFailed if any failed, else kJobCancelled if any was cancelled, else
// kTargetNotReached if any stopped short of its target, else the first other code.
int BatchExitCode(const std::vector<int>& study_codes);

// A folder name for a study's artifacts under `submit --out DIR`: the label with every
// character but [A-Za-z0-9._-] replaced by '_', made unique among `taken` (which it joins).
std::string ArtifactFolderName(const std::string& label, std::vector<std::string>* taken);

}  // namespace decima::client
