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

absl::Status CheckSeriesComplete(const std::vector<fs::path>& files) {
  struct Slice {
    fs::path file;
    Eigen::Vector3d position;
    double z = 0;
  };
  std::vector<Slice> slices;
  std::string orientation, spacing;
  long rows = -1, cols = -1;
  Eigen::Vector3d normal(0, 0, 1);
  for (const auto& f : files) {
    DcmFileFormat ff;
    if (auto st = LoadBoundedHeader(f, &ff); !st.ok()) return st;
    DcmDataset& d = *ff.getDataset();
    const OFString ipp = SmallString(d, DCM_ImagePositionPatient, true).c_str();
    const OFString iop = SmallString(d, DCM_ImageOrientationPatient, true).c_str();
    const OFString ps = SmallString(d, DCM_PixelSpacing, true).c_str();
    const Uint16 r = SmallUint16(d, DCM_Rows), co = SmallUint16(d, DCM_Columns);
    const OFString frames = SmallString(d, DCM_NumberOfFrames).c_str();
    const OFString images_in_acquisition = SmallString(d, DCM_ImagesInAcquisition).c_str();
    long expected = 0;
    if (!images_in_acquisition.empty() &&
        absl::SimpleAtoi(images_in_acquisition.c_str(), &expected) && expected > 0 &&
        static_cast<size_t>(expected) > files.size()) {
      return absl::InvalidArgumentError(absl::StrCat(files.size(), " of ", expected,
                                                     " instances (ImagesInAcquisition of ",
                                                     f.filename().string(), ")"));
    }
    auto name = f.filename().string();
    if (ipp.empty() || iop.empty() || ps.empty() || r == 0 || co == 0) {
      return absl::InvalidArgumentError(
          absl::StrCat("instance ", name,
                       " lacks ImagePositionPatient, ImageOrientationPatient, PixelSpacing, "
                       "Rows or Columns: not a slice of a volume"));
    }
    if (!frames.empty() && frames != "1") {
      return absl::InvalidArgumentError(
          absl::StrCat("instance ", name, " has ", frames.c_str(), " frames; expected 1"));
    }
    std::vector<double> p, o;
    for (absl::string_view s : absl::StrSplit(ipp.c_str(), '\\')) {
      double v = 0;
      if (absl::SimpleAtod(s, &v)) p.push_back(v);
    }
    for (absl::string_view s : absl::StrSplit(iop.c_str(), '\\')) {
      double v = 0;
      if (absl::SimpleAtod(s, &v)) o.push_back(v);
    }
    if (p.size() != 3 || o.size() != 6) {
      return absl::InvalidArgumentError(
          absl::StrCat("instance ", name, ": malformed ImagePositionPatient or orientation"));
    }
    if (slices.empty()) {
      orientation = iop.c_str();
      spacing = ps.c_str();
      rows = r;
      cols = co;
      normal = Eigen::Vector3d(o[0], o[1], o[2]).cross(Eigen::Vector3d(o[3], o[4], o[5]));
      if (normal.norm() < 1e-6) {
        return absl::InvalidArgumentError(
            absl::StrCat("instance ", name, ": degenerate orientation"));
      }
      normal.normalize();
    } else if (orientation != iop.c_str()) {
      return absl::InvalidArgumentError(absl::StrCat("more than one orientation: ", orientation,
                                                     " and ", iop.c_str(), " (", name, ")"));
    } else if (rows != r || cols != co || spacing != ps.c_str()) {
      return absl::InvalidArgumentError(absl::StrCat("inconsistent size: ", cols, "x", rows,
                                                     " spacing ", spacing, " and ", co, "x", r,
                                                     " spacing ", ps.c_str(), " (", name, ")"));
    }
    Slice s{f, Eigen::Vector3d(p[0], p[1], p[2]), 0};
    s.z = s.position.dot(normal);
    slices.push_back(std::move(s));
  }
  if (slices.size() < 2) {
    return absl::InvalidArgumentError(
        absl::StrCat(slices.size(), " slice(s): a volume needs 2 or more"));
  }
  std::sort(slices.begin(), slices.end(), [](const Slice& a, const Slice& b) { return a.z < b.z; });
  double min_gap = INFINITY;
  for (size_t i = 1; i < slices.size(); ++i) {
    const double gap = slices[i].z - slices[i - 1].z;
    if (gap < 1e-3) {
      return absl::InvalidArgumentError(absl::StrFormat(
          "two instances at the same position z=%g mm (%s, %s)", slices[i].z,
          slices[i - 1].file.filename().string(), slices[i].file.filename().string()));
    }
    min_gap = std::min(min_gap, gap);
    // Every slice on the line through the first along the normal (no gantry tilt, no shift).
    const Eigen::Vector3d off = slices[i].position - slices[0].position;
    if ((off - off.dot(normal) * normal).norm() > 0.01 + 0.01 * min_gap) {
      return absl::InvalidArgumentError(absl::StrCat("slices not stacked along their normal (",
                                                     slices[i].file.filename().string(),
                                                     "): tilted or shifted series"));
    }
  }
  for (size_t i = 1; i < slices.size(); ++i) {
    const double gap = slices[i].z - slices[i - 1].z;
    if (std::abs(gap - min_gap) > 0.01 * min_gap + 0.01) {
      const long missing = std::lround(gap / min_gap) - 1;
      return absl::InvalidArgumentError(absl::StrFormat(
          "%s between z=%g and z=%g mm (gap %g mm, expected %g mm); %d instances received",
          missing >= 1 ? absl::StrCat(missing, " slice(s) missing") : std::string("uneven spacing"),
          slices[i - 1].z, slices[i].z, gap, min_gap, slices.size()));
    }
  }
  return absl::OkStatus();
}

namespace {

// The receive `instances` (one sender's series, the set `key`) make, its state still to be
// decided; `*aborted` the newest abort mark among them. Apart from SettleSeries so that its
// steps stay on one screen.
DicomSeriesRecord NewReceive(const std::string& series_uid,
                             const std::vector<DicomInstanceRecord>& instances,
                             const std::string& key, const DicomRoute* route, int64_t* aborted) {
  const DicomInstanceRecord& last = instances.back();
  DicomSeriesRecord rec;
  rec.instance_set = key;
  rec.series_instance_uid = series_uid;
  rec.route = route != nullptr ? route->name : "";
  rec.update_ms = WallMs();
  rec.calling_ae = last.calling_ae;
  rec.called_ae = last.called_ae;
  rec.association_id = last.association_id;
  rec.instance_count = static_cast<int>(instances.size());
  rec.first_received_ms = INT64_MAX;
  int64_t newest = 0;
  for (const auto& i : instances) {
    rec.first_received_ms = std::min(rec.first_received_ms, i.received_ms);
    newest = std::max(newest, i.received_ms);
    *aborted = std::max(*aborted, i.aborted_ms);
  }
  rec.last_received_ms = newest;
  rec.receive_key = ReceiveKey(key, newest);
  return rec;
}

std::string FormatMs(int64_t ms) {
  return TimeUtil::ToString(TimeUtil::MillisecondsToTimestamp(ms));
}

}  // namespace

void DicomReceiver::SettleLoop() {
  const auto period = std::chrono::milliseconds(
      std::max<int64_t>(10, static_cast<int64_t>(options_.poll_seconds * 1000)));
  while (!stop_) {
    {
      std::unique_lock<std::mutex> lock(mu_);
      cv_.wait_for(lock, period, [this] { return wake_; });
      wake_ = false;
    }
    if (stop_) break;
    auto instances = store_->ListDicomInstances();
    if (!instances.ok()) {
      spdlog::error("dicom: {}", instances.status().ToString());
      continue;
    }
    // A series per sender: another sender's instances of the same SeriesInstanceUID are
    // another series (they never complete or replace these).
    std::map<std::pair<std::string, std::string>, std::vector<DicomInstanceRecord>> by_series;
    for (auto& i : *instances) {
      by_series[{i.calling_ae, i.series_instance_uid}].push_back(std::move(i));
    }
    const int64_t now = WallMs();
    const auto quiet_ms = static_cast<int64_t>(options_.quiet_seconds * 1000);
    const auto expiry_ms = static_cast<int64_t>(options_.incomplete_expiry_seconds * 1000);
    std::set<std::string> pending_keys;
    for (const auto& [sender_series, list] : by_series) {
      const auto& [calling_ae, series] = sender_series;
      int64_t newest = 0;
      std::vector<std::string> uids;
      for (const auto& i : list) {
        newest = std::max(newest, i.received_ms);
        uids.push_back(i.sop_instance_uid);
      }
      if (expiry_ms > 0 && now - newest >= expiry_ms) {
        auto removed = RemoveWaiting(
            store_, blobs_, calling_ae, series, v1::ReceivedSeries::EXPIRED,
            absl::StrCat("expired: no instance came for ", (now - newest) / 1000,
                         " s (--dicom-incomplete-expiry ", options_.incomplete_expiry_seconds,
                         " s); its ", list.size(), " waiting instances were removed"));
        if (!removed.ok()) spdlog::error("dicom: {}", removed.status().ToString());
        continue;
      }
      const std::string key = InstanceSetKey(calling_ae, uids);
      pending_keys.insert(key);
      // Once per set and newest arrival: the same set sent again (a retry after an abort, which
      // lifts the abort mark) is checked again.
      auto seen = checked_.find(key);
      if (now - newest < quiet_ms || (seen != checked_.end() && seen->second == newest)) continue;
      checked_[key] = newest;
      SettleSeries(series, list, key);
    }
    for (auto it = checked_.begin(); it != checked_.end();) {
      it = pending_keys.count(it->first) > 0 ? std::next(it) : checked_.erase(it);
    }
    FollowReceives();
  }
}

void DicomReceiver::SettleSeries(const std::string& series_uid,
                                 const std::vector<DicomInstanceRecord>& instances,
                                 const std::string& key) {
  const DicomInstanceRecord& last = instances.back();
  const DicomRoute* route = options_.routes.Match(last.calling_ae, last.called_ae);
  int64_t aborted = 0;
  DicomSeriesRecord rec = NewReceive(series_uid, instances, key, route, &aborted);
  const int64_t newest = rec.last_received_ms;
  const std::string owner = DicomOwner(last.calling_ae);
  auto not_queued = [&](v1::ReceivedSeries::State state, const std::string& reason) {
    rec.state = state;
    // The reason may quote the instances' own text (NumberOfFrames, ...): kept as valid UTF-8,
    // which PostgreSQL's TEXT and the answer's protobuf string both require.
    rec.reason = ValidUtf8(reason);
    spdlog::warn("dicom: series {} ({} instances from {}) not queued: {}", series_uid,
                 instances.size(), last.calling_ae, rec.reason);
    if (auto st = store_->PutDicomSeries(rec, {}); !st.ok()) {
      spdlog::error("dicom: recording series {}: {}", series_uid, st.ToString());
    }
  };
  constexpr auto kIncomplete = v1::ReceivedSeries::INCOMPLETE;
  constexpr auto kNotQueued = v1::ReceivedSeries::NOT_QUEUED;
  if (route == nullptr) return not_queued(kNotQueued, "no route for its AE titles any more");
  // An aborted association may have cut a series short anywhere, also after a contiguous run
  // of slices that the geometry check cannot tell from a whole series: wait for more.
  if (aborted >= newest) {
    return not_queued(kIncomplete,
                      absl::StrCat("the association that sent it was aborted after ",
                                   instances.size(), " instances; waiting for the rest"));
  }
  std::vector<fs::path> files;
  v1::CreateVolumeRequest vreq;
  std::vector<std::string> uids;
  for (const auto& i : instances) {
    auto path = blobs_->LocalPath(i.sha256);
    if (!path.ok())
      return not_queued(
          kNotQueued, absl::StrCat("instance ", i.sop_instance_uid, ": ", path.status().message()));
    files.push_back(*path);
    uids.push_back(i.sop_instance_uid);
    auto* f = vreq.mutable_volume()->add_files();
    f->set_path(absl::StrCat(i.sop_instance_uid, ".dcm"));
    f->set_blob(absl::StrCat("blobs/", i.sha256));
  }
  if (auto st = CheckSeriesComplete(files); !st.ok()) {
    return not_queued(kIncomplete, absl::StrCat("incomplete: ", st.message()));
  }
  const std::string request_id = absl::StrCat("dicom-", key);
  vreq.set_request_id(request_id);
  vreq.mutable_volume()->set_display_name(absl::StrCat("DICOM series ", series_uid));
  v1::ErrorDetail detail;
  // Created by the sender's principal, so that a submitter token of that name sees them and
  // readers and admins see them as any other.
  auto volume = catalog_->Create(vreq, owner, &detail);
  if (!volume.ok()) {
    return not_queued(kNotQueued, absl::StrCat("volume: ", volume.status().message()));
  }
  // The request id is the receiver's (CreateVolume and CreateJob refuse the prefix to callers),
  // but a store from before that rule may hold another principal's: never reuse it.
  if (volume->creator() != owner) {
    spdlog::error("dicom: series {} from {}: request id {} names {}, created by '{}', not {}",
                  series_uid, last.calling_ae, request_id, volume->name(), volume->creator(),
                  owner);
    return not_queued(kNotQueued, absl::StrCat("request id ", request_id, " is held by ",
                                               volume->name(), " of another creator"));
  }
  v1::JobSpec spec = route->spec;
  spec.set_volume(volume->name());
  // A route that chose no outputs: the defaults, plus the region surfaces, which go back to
  // the PACS as Encapsulated STL beside the SEG (jobs/dicom_results.h).
  if (spec.outputs().empty()) {
    for (const std::string& o : pipeline::JobSpec{}.outputs) spec.add_outputs(o);
    spec.add_outputs("stl");
  }
  auto normalized = NormalizeJobSpec(spec);
  if (!normalized.ok()) {
    return not_queued(kNotQueued, absl::StrCat("spec: ", normalized.status().message()));
  }
  bool created = false;
  const std::string id = NewId();
  auto job = store_->CreateJob(id, *normalized, request_id, options_.max_queued, owner, &created);
  if (!created) data_dir_->RemoveJob(id);
  if (options_.audit)
    options_.audit->RecordSystem(owner, "DicomCreateJob", job.ok() ? job->name() : "", job.status(),
                                 rec.association_id);
  if (!job.ok()) return not_queued(kNotQueued, absl::StrCat("job: ", job.status().ToString()));
  if (job->creator() != owner) {
    spdlog::error("dicom: series {} from {}: request id {} names {}, created by '{}', not {}",
                  series_uid, last.calling_ae, request_id, job->name(), job->creator(), owner);
    return not_queued(kNotQueued, absl::StrCat("request id ", request_id, " is held by ",
                                               job->name(), " of another creator"));
  }
  // Complete and queued (or the job of the same set reused): FollowReceives advances it with
  // its job and sends the results to this receive's route.
  rec.state = v1::ReceivedSeries::QUEUED;
  rec.job = job->name();
  rec.reason.clear();
  rec.results_pending = true;
  if (!created) {
    spdlog::info(
        "dicom: series {} re-sent by {} ({} instances): same set as {}, no new job; its results "
        "go to route {} too",
        series_uid, last.calling_ae, instances.size(), job->name(), route->name);
  } else {
    spdlog::info(
        "job {} QUEUED from DICOM series {} ({} instances from {}, newest by association {}, "
        "route {})",
        id, series_uid, instances.size(), last.calling_ae, rec.association_id, route->name);
  }
  if (auto st = store_->PutDicomSeries(rec, uids); !st.ok()) {
    spdlog::error("dicom: recording series {}: {}", series_uid, st.ToString());
    return;
  }
  CloseEarlierReceives(store_, last.calling_ae, series_uid, rec.receive_key,
                       v1::ReceivedSeries::COMPLETE, job->name(),
                       absl::StrCat("completed by the receive of ", FormatMs(newest)));
  if (created) pool_->Notify();
}

void DicomReceiver::FollowReceives() {
  auto pending = store_->ListDicomSeries(/*pending_only=*/true, 100);
  if (!pending.ok()) {
    spdlog::error("dicom: {}", pending.status().ToString());
    return;
  }
  const int64_t now = WallMs();
  for (DicomSeriesRecord rec : *pending) {
    if (stop_) return;
    const DicomSeriesRecord before = rec;
    auto id = ParseName(rec.job, "jobs", "job");
    if (!id.ok()) {
      rec.results_pending = false;  // nothing to follow
    } else if (auto job = store_->GetJob(*id); !job.ok()) {
      if (job.status().code() != absl::StatusCode::kNotFound) continue;  // retried next period
      rec.state = v1::ReceivedSeries::FAILED;
      rec.reason = absl::StrCat(rec.job, " was deleted before it finished");
      rec.results_pending = false;
    } else if (job->state() == v1::QUEUED || job->state() == v1::RUNNING) {
      rec.state =
          job->state() == v1::QUEUED ? v1::ReceivedSeries::QUEUED : v1::ReceivedSeries::RUNNING;
    } else if (job->state() != v1::SUCCEEDED) {
      rec.state = v1::ReceivedSeries::FAILED;
      rec.reason =
          absl::StrCat("job ", v1::JobState_Name(job->state()), ": ", job->error().message());
      rec.send_status = "nothing sent: the job did not succeed";
      rec.results_pending = false;
    } else {
      rec.state = v1::ReceivedSeries::SUCCEEDED;
      const DicomRoute* route = options_.routes.Find(rec.route);
      std::vector<fs::path> files;
      for (const auto& a : job->artifacts()) {
        const std::string& n = a.file_name();
        if (n.size() > 4 && n.compare(n.size() - 4, 4, ".dcm") == 0) {
          files.push_back(data_dir_->ArtifactsDir(*id) / n);
        }
      }
      if (route == nullptr || !route->destination.configured()) {
        rec.send_status = absl::StrCat("nothing sent: route '", rec.route, "' has no destination");
        rec.results_pending = false;
      } else if (files.empty()) {
        rec.send_status = "nothing sent: the job has no DICOM artifact";
        rec.results_pending = false;
      } else if (next_send_ms_.count(rec.receive_key) == 0 ||
                 now >= next_send_ms_[rec.receive_key]) {
        DicomDestination dest = route->destination;
        dest.calling_aet = options_.aet;
        const auto t0 = std::chrono::steady_clock::now();
        auto sent = SendDicomFiles(dest, files);
        if (options_.audit)
          options_.audit->RecordSystem(job->creator(), "DicomSendResults", rec.job, sent.status(),
                                       rec.association_id);
        const double secs =
            std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
        if (sent.ok()) {
          rec.state = v1::ReceivedSeries::SENT;
          rec.send_status = absl::StrCat("sent: ", *sent);
          rec.results_pending = false;
          spdlog::info("dicom: results of {} {} (route {}) in {:.3f} s", rec.job, *sent, rec.route,
                       secs);
        } else {
          const int attempts = ++send_attempts_[rec.receive_key];
          rec.send_status =
              absl::StrCat("attempt ", attempts, " failed: ", sent.status().ToString());
          spdlog::warn("dicom: results of {} (route {}): {}", rec.job, rec.route, rec.send_status);
          if (attempts < 3) {
            next_send_ms_[rec.receive_key] = now + 5000;
          } else {
            rec.state = v1::ReceivedSeries::SEND_FAILED;
            rec.results_pending = false;
          }
        }
      }
    }
    if (!rec.results_pending) {
      send_attempts_.erase(rec.receive_key);
      next_send_ms_.erase(rec.receive_key);
    }
    if (rec.state == before.state && rec.results_pending == before.results_pending &&
        rec.send_status == before.send_status && rec.reason == before.reason) {
      continue;  // nothing new: no write every period
    }
    rec.update_ms = now;
    if (auto st = store_->PutDicomSeries(rec, {}); !st.ok()) {
      spdlog::error("dicom: recording the outcome of {}: {}", rec.job, st.ToString());
    }
  }
}

}  // namespace decima::server
