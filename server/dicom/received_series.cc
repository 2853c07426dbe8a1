#include "server/dicom/dicom_receiver.h"
#include "server/dicom/receiver_parts.h"

// clang-format off
#include "dcmtk/config/osconfig.h"  // must come first
// clang-format on
#include "dcmtk/dcmdata/dcdeftag.h"
#include "dcmtk/dcmdata/dcfilefo.h"
#include "dcmtk/dcmdata/dcmetinf.h"
#include "dcmtk/dcmdata/dcuid.h"
#include "dcmtk/dcmnet/diutil.h"
#include "dcmtk/dcmnet/dul.h"
#include "dcmtk/dcmnet/scpthrd.h"
#include "dcmtk/oflog/oflog.h"

#include <arpa/inet.h>
#include <netdb.h>
#include <netinet/in.h>
#include <netinet/tcp.h>
#include <poll.h>
#include <sys/ioctl.h>
#include <sys/mman.h>
#include <sys/socket.h>
#include <sys/statvfs.h>
#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <chrono>
#include <cmath>
#include <cstring>
#include <fstream>

#include <Eigen/Core>
#include <Eigen/Geometry>

#include <google/protobuf/util/time_util.h>

#include "absl/strings/escaping.h"
#include "absl/strings/match.h"
#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "absl/strings/str_join.h"
#include "absl/strings/str_split.h"
#include "core/common/utf8.h"
#include "decima/v1/errors.pb.h"
#include "server/dicom/dicom_sender.h"
#include "server/files/volume_catalog.h"
#include "server/jobs/job_spec.h"
#include "server/util/ids.h"
#include "server/util/sha256.h"
#include "spdlog/spdlog.h"

namespace decima::server {
namespace fs = std::filesystem;
using google::protobuf::util::TimeUtil;

// The key of one sender's set of instances: the sender is part of it, so the request id made
// from it ("dicom-<key>") is another for the same SOP Instance UIDs from another sender.
std::string InstanceSetKey(const std::string& calling_ae, std::vector<std::string> sop_uids) {
  std::sort(sop_uids.begin(), sop_uids.end());
  Sha256 h;
  h.Update(calling_ae.data(), calling_ae.size());
  h.Update("\n", 1);
  for (const auto& u : sop_uids) {
    h.Update(u.data(), u.size());
    h.Update("\n", 1);
  }
  return h.HexDigest();
}

// A check's receive: the set at its newest arrival (the same set re-checked after a restart is
// the same receive; sent again later, a new one).
std::string ReceiveKey(const std::string& instance_set, int64_t newest_ms) {
  return absl::StrCat(instance_set, "@", newest_ms);
}

// Earlier INCOMPLETE receives of the sender's series whose instances a later receive consumed or
// removed: they take the outcome (`state`, `job`, `reason`) instead of waiting for ever in the
// history. Bounded by the newest 1000 rows.
void CloseEarlierReceives(JobStore* store, const std::string& calling_ae,
                          const std::string& series_uid, const std::string& except_key,
                          v1::ReceivedSeries::State state, const std::string& job,
                          const std::string& reason) {
  auto rows = store->ListDicomSeries(/*pending_only=*/false, 1000);
  if (!rows.ok()) {
    spdlog::error("dicom: {}", rows.status().ToString());
    return;
  }
  for (DicomSeriesRecord r : *rows) {
    if (r.calling_ae != calling_ae || r.series_instance_uid != series_uid ||
        r.receive_key == except_key || r.state != v1::ReceivedSeries::INCOMPLETE) {
      continue;
    }
    r.state = state;
    r.job = job;
    r.reason = reason;
    r.update_ms = WallMs();
    if (auto st = store->PutDicomSeries(r, {}); !st.ok()) {
      spdlog::error("dicom: recording series {}: {}", series_uid, st.ToString());
    }
  }
}

// Removes the waiting instances of a sender's series (expired or deleted), records the outcome
// as the receive of that set (`state`, `reason`), closes the sender's earlier INCOMPLETE
// receives of it, and frees the blobs nothing else holds.
absl::StatusOr<RemovedSeries> RemoveWaiting(JobStore* store, BlobStore* blobs,
                                            const std::string& calling_ae,
                                            const std::string& series_uid,
                                            v1::ReceivedSeries::State state,
                                            const std::string& reason) {
  auto removed = store->RemoveDicomInstances(calling_ae, series_uid);
  if (!removed.ok()) return removed.status();
  RemovedSeries out;
  if (removed->empty()) return out;
  out.instances = static_cast<int>(removed->size());
  std::vector<std::string> uids, shas;
  int64_t first = INT64_MAX, newest = 0;
  for (const auto& i : *removed) {
    uids.push_back(i.sop_instance_uid);
    shas.push_back(i.sha256);
    first = std::min(first, i.received_ms);
    newest = std::max(newest, i.received_ms);
  }
  const std::string set = InstanceSetKey(calling_ae, uids);
  DicomSeriesRecord rec;
  rec.receive_key = ReceiveKey(set, newest);
  // The row of this set's check, when it was checked: its route and counts stay.
  if (auto rows = store->ListDicomSeries(false, 1000); rows.ok()) {
    for (const auto& r : *rows) {
      if (r.receive_key == rec.receive_key) rec = r;
    }
  }
  rec.instance_set = set;
  rec.series_instance_uid = series_uid;
  rec.calling_ae = calling_ae;
  rec.called_ae = removed->back().called_ae;
  rec.association_id = removed->back().association_id;
  rec.instance_count = out.instances;
  rec.first_received_ms = first;
  rec.last_received_ms = newest;
  rec.state = state;
  rec.reason = reason;
  rec.job.clear();
  rec.results_pending = false;
  std::sort(shas.begin(), shas.end());
  shas.erase(std::unique(shas.begin(), shas.end()), shas.end());
  BlobSweepPolicy now;
  now.grace = std::chrono::seconds(0);
  // A blob another sender's instance or a volume holds stays (identical bytes are one blob).
  const BlobSweepStats swept = blobs->Sweep(
      now,
      [store](const std::string& sha) {
        auto used = store->BlobInUse(sha);
        return !used.ok() || *used;
      },
      &shas);
  out.freed_bytes = swept.bytes_freed;
  // Recorded after the sweep: whoever reads the EXPIRED or DELETED row finds its bytes gone.
  rec.update_ms = WallMs();
  if (auto st = store->PutDicomSeries(rec, {}); !st.ok()) {
    spdlog::error("dicom: recording series {}: {}", series_uid, st.ToString());
  }
  CloseEarlierReceives(store, calling_ae, series_uid, rec.receive_key, state, "", reason);
  spdlog::info("dicom: series {} from {}: {} instances removed ({} bytes freed): {}", series_uid,
               absl::CHexEscape(calling_ae), out.instances, out.freed_bytes, reason);
  return out;
}

std::string DicomOwner(const std::string& calling_ae) { return absl::StrCat("dicom:", calling_ae); }

absl::Status RefuseReceiverRequestId(const std::string& request_id) {
  if (!absl::StartsWith(request_id, "dicom-")) return absl::OkStatus();
  // Otherwise a submitter who computes a series' id before it arrives has the receiver reuse
  // its job and send that job's results as the sender's.
  return absl::InvalidArgumentError(absl::StrCat(
      "request_id: '", request_id, "': the prefix 'dicom-' is reserved for the DICOM receiver"));
}

absl::StatusOr<RemovedSeries> DeleteReceivedSeries(
    JobStore* store, BlobStore* blobs, const std::string& series_uid, const std::string& calling_ae,
    const std::string& deleted_by,
    const std::function<absl::Status(const std::string& owner)>& may_delete) {
  if (!IsDicomUid(series_uid)) {
    return absl::InvalidArgumentError(
        absl::StrCat("series_instance_uid: '", absl::CHexEscape(series_uid),
                     "' is not a DICOM UID (digits and dots, at most 64 characters)"));
  }
  if (!calling_ae.empty() && !IsAeTitle(calling_ae)) {
    return absl::InvalidArgumentError(absl::StrCat("calling_ae: '", absl::CHexEscape(calling_ae),
                                                   "' is not an AE title (printable ASCII, 1-16 "
                                                   "characters)"));
  }
  auto instances = store->ListDicomInstances();
  if (!instances.ok()) return instances.status();
  std::set<std::string> senders;
  for (const auto& i : *instances) {
    if (i.series_instance_uid == series_uid && (calling_ae.empty() || i.calling_ae == calling_ae)) {
      senders.insert(i.calling_ae);
    }
  }
  if (senders.empty()) {
    return absl::NotFoundError(
        absl::StrCat("no instance of series ", series_uid,
                     calling_ae.empty() ? "" : absl::StrCat(" from ", calling_ae), " waits"));
  }
  RemovedSeries total;
  absl::Status refused;
  int allowed = 0;
  for (const auto& sender : senders) {
    if (absl::Status may = may_delete(DicomOwner(sender)); !may.ok()) {
      refused = may;
      continue;
    }
    ++allowed;
    auto removed = RemoveWaiting(store, blobs, sender, series_uid, v1::ReceivedSeries::DELETED,
                                 absl::StrCat("deleted by ", deleted_by));
    if (!removed.ok()) return removed.status();
    total.instances += removed->instances;
    total.freed_bytes += removed->freed_bytes;
  }
  if (allowed == 0) return refused;
  return total;
}

namespace {

v1::ReceivedSeries ToProto(const DicomSeriesRecord& r) {
  v1::ReceivedSeries out;
  out.set_series_instance_uid(r.series_instance_uid);
  out.set_calling_ae(r.calling_ae);
  out.set_called_ae(r.called_ae);
  out.set_instance_count(r.instance_count);
  // Rows written before the state column: derived from what they hold.
  out.set_state(r.state != v1::ReceivedSeries::STATE_UNSPECIFIED ? r.state
                : r.job.empty()                                  ? v1::ReceivedSeries::NOT_QUEUED
                                                                 : v1::ReceivedSeries::QUEUED);
  out.set_job(r.job);
  out.set_reason(ValidUtf8(r.reason));  // also rows stored before reasons were made valid
  out.set_route(r.route);
  out.set_owner(r.calling_ae.empty() ? "" : DicomOwner(r.calling_ae));
  *out.mutable_first_receive_time() = TimeUtil::MillisecondsToTimestamp(r.first_received_ms);
  *out.mutable_last_receive_time() = TimeUtil::MillisecondsToTimestamp(r.last_received_ms);
  out.set_send_status(ValidUtf8(r.send_status));
  out.set_association_id(r.association_id);
  return out;
}

}  // namespace

absl::StatusOr<ReceivedSeriesPage> ListReceivedSeries(JobStore* store, const std::string& owner,
                                                      int page_size,
                                                      const std::string& page_token) {
  size_t offset = 0;
  if (!page_token.empty() &&
      (page_token[0] != 'r' || !absl::SimpleAtoi(page_token.substr(1), &offset))) {
    return absl::InvalidArgumentError(
        absl::StrCat("page_token '", page_token, "' is not a token this server returned"));
  }
  const size_t size = page_size <= 0 ? 50 : std::min(page_size, 1000);
  auto instances = store->ListDicomInstances();
  if (!instances.ok()) return instances.status();
  auto rows = store->ListDicomSeries(/*pending_only=*/false, 1000);
  if (!rows.ok()) return rows.status();
  std::set<std::string> recorded;
  for (const auto& r : *rows) recorded.insert(r.receive_key);

  // Each sender's waiting instances not checked as they are now: a RECEIVING entry (their
  // earlier checks, if any, are rows of their own).
  std::map<std::pair<std::string, std::string>, std::vector<const DicomInstanceRecord*>> waiting;
  for (const auto& i : *instances) waiting[{i.calling_ae, i.series_instance_uid}].push_back(&i);
  std::vector<v1::ReceivedSeries> all;
  for (const auto& [sender_series, list] : waiting) {
    std::vector<std::string> sops;
    int64_t first = INT64_MAX, last = 0;
    for (const auto* i : list) {
      sops.push_back(i->sop_instance_uid);
      first = std::min(first, i->received_ms);
      last = std::max(last, i->received_ms);
    }
    if (recorded.count(ReceiveKey(InstanceSetKey(sender_series.first, sops), last)) > 0) continue;
    DicomSeriesRecord r;
    r.state = v1::ReceivedSeries::RECEIVING;
    r.first_received_ms = first;
    r.last_received_ms = last;
    r.series_instance_uid = sender_series.second;
    r.calling_ae = sender_series.first;
    r.called_ae = list.back()->called_ae;
    r.association_id = list.back()->association_id;
    r.instance_count = static_cast<int>(list.size());
    all.push_back(ToProto(r));
  }
  for (const auto& r : *rows) all.push_back(ToProto(r));
  std::stable_sort(all.begin(), all.end(), [](const auto& a, const auto& b) {
    return TimeUtil::TimestampToMilliseconds(a.last_receive_time()) >
           TimeUtil::TimestampToMilliseconds(b.last_receive_time());
  });
  if (!owner.empty()) {
    std::erase_if(all, [&](const v1::ReceivedSeries& r) { return r.owner() != owner; });
  }
  // A token past the end (the list shrank, or it was made up) is an empty last page; compared
  // without offset + size, which a made-up offset near SIZE_MAX wraps around.
  ReceivedSeriesPage page;
  if (offset >= all.size()) return page;
  const size_t end = all.size() - offset > size ? offset + size : all.size();
  for (size_t k = offset; k < end; ++k) page.series.push_back(std::move(all[k]));
  if (end < all.size()) page.next_page_token = absl::StrCat("r", end);
  return page;
}

}  // namespace decima::server
