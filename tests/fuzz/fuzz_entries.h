// The entry functions of the fuzz targets, shared by the libFuzzer binaries (clang,
// DECIMA_FUZZ=ON) and by fuzz_replay_test, which runs every seed of the corpora through them in
// the normal build. Each returns 0; a contract violation aborts (libFuzzer reports it as a crash,
// the replay test dies).
#pragma once

#include <cstddef>
#include <cstdint>
#include <string_view>

namespace decima::fuzz {

// The bytes as a .vtu file read by ReadVtu: it must return a Status, and a mesh it accepts must
// satisfy the TetMesh invariants ReadVtu promises (consistent sizes, indices in range, positive
// volumes, finite scalars, labels and regions < 8).
int ReadVtuEntry(const uint8_t* data, size_t size);

// The bytes as transfer-function JSON: ParseTransferFunction must return a Status, and a function
// it accepts must serialize (TransferFunctionToJson) to JSON it accepts again.
int TransferFunctionEntry(const uint8_t* data, size_t size);

// Volume readers. Inputs of several files (a header and its detached data, or the slices of a
// DICOM folder) are one byte string cut at kFileSeparator.
inline constexpr std::string_view kFileSeparator = "\n--decima-fuzz-next-file--\n";

// First byte: bit 0 chooses a single file (.nii) or a pair (.hdr + .img). ReadNifti must return
// a Status; a volume it returns passes Validate, and ProbeVolume accepts the file with the same
// dims (the server decides on the probe alone).
int NiftiEntry(const uint8_t* data, size_t size);
// As NiftiEntry for ReadMetaImage: .mha, or (bit 0) .mhd with the detached files a.raw, a.zraw.
int MetaImageEntry(const uint8_t* data, size_t size);
// As NiftiEntry for ReadNrrd: .nrrd, or (bit 0) .nhdr with the detached files a.raw, a.raw.gz.
int NrrdEntry(const uint8_t* data, size_t size);
// The header check `decima submit` runs before an upload (client/cli/volume_upload.h: ProbeVolume
// on the file alone, issue 30). First byte % 6 picks the file: .nii, .hdr + .img, .mha,
// .mhd + a.raw/a.zraw, .nrrd, .nhdr + a.raw/a.raw.gz; the rest as the entries above. The probe
// must return a Status whose error names the file; dims it accepts are each >= 1 with a product
// <= kMaxVoxels (so CheckJobMemory's ValidateVolumeSize takes them: a file the server would
// accept is never refused by the pre-upload check).
int VolumeHeaderEntry(const uint8_t* data, size_t size);
// Each part is one file of a folder: every part goes through the structural preflight, the
// folder through ListDicomSeries, ReadDicomSeries (GDCM) and ReadVolume, which must agree and
// never crash or abort; a volume returned passes Validate.
int DicomEntry(const uint8_t* data, size_t size);

// The bytes as a .levels file (ParseLevels): it must return a Status, and a record it accepts
// must be a valid simplicial map (ValidateLevels) that the writer turns into a file read back
// the same.
int LevelsEntry(const uint8_t* data, size_t size);

// The streamed simplifier's window records (core/simplify/stream.h, StreamJournal) as an earlier
// attempt of a job left them, read back by SimplifyStreamed on a small fixed grid (4 windows a
// pass). First byte: bits 0-1 the pass the records are offered for; bit 2 set: that pass's real
// records, patched by the rest of the input taken as (record, offset low, offset high, byte)
// quadruples; clear: the rest is the records themselves, window 0 first, cut at kFileSeparator.
// The run must end with a Status (never crash, hang or run out of its arrays); an OK result is a
// mesh whose arrays agree and whose indices are in range; the real records unpatched give the
// run's own mesh. "Accepted": at least one record was read back.
int StreamWindowEntry(const uint8_t* data, size_t size);

// Upload + GetUploadStatus through the real service (in-process gRPC, LocalBlobStore in a temp
// folder). The input chooses honest or fuzzed digest, size and offset, chunking, an interrupted
// stream and its resume. Every answer has an expected code (not UNKNOWN/INTERNAL); an honest
// upload succeeds; a blob the server accepted is exactly the declared bytes.
int UploadEntry(const uint8_t* data, size_t size);

// CreateVolume through the real service: a manifest of 1-4 files (fuzzed or typical names,
// uploaded, missing or malformed blob names, any format value). Every answer has an expected
// code; a refused request leaves no volume folder; a created volume has its files materialized,
// positive dims, answers GetVolume (and a retry with its request_id), and DeleteVolume removes it.
int CreateVolumeEntry(const uint8_t* data, size_t size);

// One instance as the DICOM receiver gets it from a C-STORE (DicomReceiver::StoreInstance, real
// SQLite and blob stores in a temp folder): the first byte chooses the calling AE title (valid
// or not), the rest is the file. It is stored (one row naming its series, its UIDs, the AE
// titles and the blob of exactly these bytes) or refused as not understood, with no row and no
// blob kept; an instance from a calling AE that is no AE title is refused.
int DicomReceiveEntry(const uint8_t* data, size_t size);

// Each part is one file of a folder given to `decima submit --each` (parts alternate between
// the folder and a subfolder): FindStudies (client/batch.h, DCMTK up to group 0020) returns
// studies or says why not; every study is a DICOM series whose files are the folder's, each in
// one study, each carrying the study's SeriesInstanceUID. Accepted: at least one study.
int BatchStudiesEntry(const uint8_t* data, size_t size);

// A job's stage checkpoint (core/pipeline/checkpoint.h), data on a shared disk that may be torn
// or damaged. First byte: bit 0 chooses the simplify payload (else segment), bit 1 the whole file
// through ReadCheckpoint under the key "k" (else the payload parser alone). A payload the parser
// accepts has consistent sizes and in-range indices and serializes back to the same bytes.
int CheckpointEntry(const uint8_t* data, size_t size);

// The parts (at most 4) as the instances of one received series, checked by CheckSeriesComplete
// (the settle loop's check, over the receiver's bounded header reader): OK or INVALID_ARGUMENT,
// OK only for 2 or more files, and the same verdict for the files in reverse order.
int DicomSeriesCheckEntry(const uint8_t* data, size_t size);

// Whether the last input of the volume, checkpoint, DICOM, DICOM receive, series check, Upload
// or CreateVolume entries was accepted (a volume read, an instance stored, an upload stored, a
// volume created): the replay test checks that the seeds named ok-* are, so the corpora keep
// inputs that reach past the header checks.
bool LastInputAccepted();
void SetLastInputAccepted(bool accepted);

}  // namespace decima::fuzz
