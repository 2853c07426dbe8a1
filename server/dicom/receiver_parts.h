// What the parts of the DICOM receiver (dicom_receiver.h) share, for the dicom wing's own files
// only:
//   dicom_receiver.cc      the SCP: the listening socket, associations and their timeouts,
//                          C-ECHO and C-STORE, storing an instance (blob + store row)
//   dicom_header.cc        an instance's header read bounded (its UIDs, the series check's
//                          attributes)
//   dicom_series_check.cc  the settle loop: a quiet series checked for completeness
//                          (CheckSeriesComplete), made a volume and a job (SettleSeries), its
//                          job followed and its results sent
//   received_series.cc     the received-series history: listing, deleting and expiring what
//                          waits
#pragma once

// clang-format off
#include "dcmtk/config/osconfig.h"  // must come first
// clang-format on
#include "dcmtk/dcmdata/dcfilefo.h"

#include <cstdint>
#include <filesystem>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "server/dicom/dicom_receiver.h"
#include "server/files/blob_store.h"
#include "server/store/job_store.h"

namespace decima::server {

// Milliseconds since the epoch, the clock of every received_ms and update_ms.
int64_t WallMs();

// An AE title as PS3.5 6.2 allows it: printable ASCII without '\', 1-16 characters.
bool IsAeTitle(const std::string& ae);

// A UID as PS3.5 9.1 defines it: digits and dots, at most 64 characters.
bool IsDicomUid(const std::string& uid);

struct InstanceHeader {
  std::string series_uid, sop_uid, sop_class_uid;
};

// The header of `file` parsed by DCMTK from its first 64 KiB only, no value longer than 1 KiB
// read, nesting bounded. INVALID_ARGUMENT naming the file for a deflated transfer syntax or a
// header DCMTK cannot parse.
absl::Status LoadBoundedHeader(const std::filesystem::path& file, DcmFileFormat* ff);
// `tag`'s value as a string, empty when absent or too long to have been read.
std::string SmallString(DcmItem& d, const DcmTagKey& tag, bool all_values = false);
Uint16 SmallUint16(DcmItem& d, const DcmTagKey& tag);
// The instance's series, SOP instance and SOP class UIDs; INVALID_ARGUMENT when the first two
// are missing or no UIDs.
absl::StatusOr<InstanceHeader> ReadUids(const std::filesystem::path& file);

// The key of one sender's set of instances (sha256 of the sender and the sorted SOP Instance
// UIDs).
std::string InstanceSetKey(const std::string& calling_ae, std::vector<std::string> sop_uids);
// A check's receive: the set at its newest arrival.
std::string ReceiveKey(const std::string& instance_set, int64_t newest_ms);
// Earlier INCOMPLETE receives of the sender's series take the outcome of a later one.
void CloseEarlierReceives(JobStore* store, const std::string& calling_ae,
                          const std::string& series_uid, const std::string& except_key,
                          v1::ReceivedSeries::State state, const std::string& job,
                          const std::string& reason);
// Removes the waiting instances of a sender's series (expired or deleted), records the outcome
// and frees the blobs nothing else holds.
absl::StatusOr<RemovedSeries> RemoveWaiting(JobStore* store, BlobStore* blobs,
                                            const std::string& calling_ae,
                                            const std::string& series_uid,
                                            v1::ReceivedSeries::State state,
                                            const std::string& reason);

}  // namespace decima::server
