// The JobStore's PACS receiver methods for stores that do not keep that state (test doubles):
// they say so, and the DICOM receiver refuses to start on such a store.
#include "absl/strings/str_cat.h"
#include "server/store/job_store.h"

namespace decima::server {
namespace {
absl::Status NotKept(const char* method) {
  return absl::UnimplementedError(
      absl::StrCat("job store: ", method, ": this store keeps no DICOM receiver state"));
}
}  // namespace

absl::Status JobStore::PutDicomInstance(const DicomInstanceRecord&) {
  return NotKept("PutDicomInstance");
}
absl::StatusOr<std::vector<DicomInstanceRecord>> JobStore::ListDicomInstances() {
  return NotKept("ListDicomInstances");
}
absl::Status JobStore::MarkDicomSeriesAborted(const std::string&, const std::string&, int64_t) {
  return NotKept("MarkDicomSeriesAborted");
}
absl::Status JobStore::PutDicomSeries(const DicomSeriesRecord&, const std::vector<std::string>&) {
  return NotKept("PutDicomSeries");
}
absl::StatusOr<std::vector<DicomSeriesRecord>> JobStore::ListDicomSeries(bool, int) {
  return NotKept("ListDicomSeries");
}
absl::StatusOr<std::vector<DicomInstanceRecord>> JobStore::RemoveDicomInstances(
    const std::string&, const std::string&) {
  return NotKept("RemoveDicomInstances");
}
absl::StatusOr<int64_t> JobStore::DicomWaitingBytes(const std::string&) {
  return NotKept("DicomWaitingBytes");
}

}  // namespace decima::server
