// The job store: jobs, their event logs and the volumes they read, behind one interface so that
// the embedded SQLite store can be replaced by a PostgreSQL one shared by many replicas
// (ClaimNext as `FOR UPDATE SKIP LOCKED`, leases, LISTEN/NOTIFY instead of the in-process
// listener).
//
// Invariants kept by every implementation:
//  - a job's events are numbered 1, 2, 3, ... without gaps; each state change writes its event
//    in the same transaction as the state, so the log and the job never disagree;
//  - a RUNNING job has exactly one lease: an owner and an epoch (fencing token). Every claim of a
//    job increments its epoch, and every renew, progress and finish must present the lease of
//    the current claim, so a holder that lost its lease (paused past expiry, job re-queued and
//    claimed again, perhaps by the same owner) changes nothing; ClaimNext never hands a job to
//    two holders;
//  - the listener is called after commit, in sequence order per job.
// Thread-safety: all methods may be called from any thread.
#pragma once

#include <chrono>
#include <cstdint>
#include <functional>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include <google/protobuf/timestamp.pb.h>
#include "absl/status/statusor.h"

#include "decima/v1/jobs.pb.h"
#include "decima/v1/volumes.pb.h"

namespace decima::server {

using EventListener = std::function<void(const std::string& job_id, const v1::JobEvent& event)>;

struct JobPage {
  std::vector<v1::Job> jobs;
  std::string next_page_token;
};

struct VolumePage {
  std::vector<v1::Volume> volumes;
  std::string next_page_token;
};

// The proof of one claim of one job.
struct Lease {
  std::string job_id;
  std::string owner;  // unique per server process
  int64_t epoch = 0;  // increments with every claim of the job
};

struct Claim {
  v1::Job job;  // as claimed: RUNNING, attempts counted
  Lease lease;
};

// What RecoverLeases did.
struct Recovered {
  std::vector<std::string> requeued;
  std::vector<std::string> failed;
};

// The PACS receiver's state (server/dicom_receiver.h), kept in the job store so that a restart
// loses neither instances received but not yet grouped into a job nor results not yet sent.
// Everything is keyed by the sender (the calling AE title, whose principal "dicom:<AE>" creates
// the volume and job): two senders of the same SeriesInstanceUID or SOP Instance UID never see,
// complete or replace each other's instances.
struct DicomInstanceRecord {
  std::string series_instance_uid;
  // Unique per calling_ae: the same bytes again replace the row, other bytes are refused.
  std::string sop_instance_uid;
  std::string sha256;  // the instance's file in the blob store
  std::string calling_ae, called_ae;
  int64_t received_ms = 0;  // wall clock, ms since the epoch
  // When an association that sent instances of this series was aborted while this instance
  // was held (0 never): stored, so a restart still queues no job for a series cut short.
  int64_t aborted_ms = 0;
  int64_t size_bytes = 0;  // of the file: a sender's waiting bytes count against its quota
  // The association that brought it (DicomReceiver: an id per accepted association); "" for
  // instances stored before associations had ids.
  std::string association_id;
};

// One receive of a series: the instances of one sender's series checked together (or refused,
// expired, deleted), and what became of them: queued as a job, or not and why, then the job's
// state and the send of its results. Every receive keeps its own row (the history that
// `decima series` shows); a later receive never overwrites an earlier one.
struct DicomSeriesRecord {
  // Key: "<instance_set>@<newest arrival ms>" for a check (the same set checked again after a
  // restart is the same receive, the same set sent again later a new one), other keys for
  // refused instances.
  std::string receive_key;
  std::string instance_set;  // sha256 of the calling AE title and the sorted SOP Instance UIDs
  std::string series_instance_uid;
  std::string job;     // "jobs/{id}" when a job was queued (or reused), else ""
  std::string reason;  // why it is not (or no longer) waiting for its job ("" when it is)
  std::string route;   // the route that chose the spec and destination
  // The receiver still follows this receive: its job's state, then the send of its results.
  bool results_pending = false;
  std::string send_status;  // last send attempt: "" none, "sent ...", or the error
  int64_t update_ms = 0;
  // What decima.v1.ReceivedSeries shows of the receive.
  v1::ReceivedSeries::State state = v1::ReceivedSeries::STATE_UNSPECIFIED;
  std::string calling_ae, called_ae;  // of the newest instance
  int instance_count = 0;
  int64_t first_received_ms = 0, last_received_ms = 0;
  // The association of the newest instance (decima.v1.ReceivedSeries.association_id).
  std::string association_id;
};

bool IsFinal(v1::JobState state);

// The wall clock with nanoseconds (protobuf 3.21's TimeUtil::GetCurrentTime drops them here).
google::protobuf::Timestamp NowTimestamp();

class JobStore {
 public:
  virtual ~JobStore() = default;

  // Called after every committed event. Set once, before serving. A shared store calls it for
  // the events of every replica, from its own thread.
  virtual void SetListener(EventListener listener) = 0;
  // The jobs watched in this process (EventBus::ActiveJobs). A shared store whose event feed
  // was interrupted re-reads their events from the store when it is back. Set once, before
  // serving; an embedded store never loses its feed and ignores it.
  virtual void SetWatchedJobs(std::function<std::vector<std::string>()> watched) { (void)watched; }

  // Queues a job with `id`, recording `creator` (the caller's principal) in Job.creator. With a
  // non-empty `request_id` already used, returns the job created then and `*created` = false.
  // RESOURCE_EXHAUSTED when `max_queued` jobs are already queued.
  virtual absl::StatusOr<v1::Job> CreateJob(const std::string& id, const v1::JobSpec& spec,
                                            const std::string& request_id, int max_queued,
                                            const std::string& creator, bool* created) = 0;
  virtual absl::StatusOr<v1::Job> GetJob(const std::string& id) = 0;
  // Newest first. `states` empty = all. `creator` non-empty: only jobs whose Job.creator equals
  // it (a submitter's own; paging then runs over those only). NOT_FOUND never;
  // INVALID_ARGUMENT for a bad token.
  virtual absl::StatusOr<JobPage> ListJobs(const std::vector<v1::JobState>& states,
                                           const std::string& creator, int page_size,
                                           const std::string& page_token) = 0;
  virtual absl::StatusOr<int64_t> CountJobs(v1::JobState state) = 0;

  // Oldest queued job -> RUNNING with a new lease for `owner` until now + lease_ms; nullopt if
  // none is queued.
  virtual absl::StatusOr<std::optional<Claim>> ClaimNext(const std::string& owner,
                                                         int64_t lease_ms) = 0;
  // Extends the lease to now + lease_ms. FAILED_PRECONDITION if `lease` is not the job's
  // current lease (lapsed and re-queued, claimed again, finished).
  virtual absl::Status RenewLease(const Lease& lease, int64_t lease_ms) = 0;
  // Appends a progress event of the RUNNING job `lease` holds (FAILED_PRECONDITION otherwise).
  virtual absl::Status AppendProgress(const Lease& lease, const v1::Progress& progress) = 0;
  // RUNNING (held by `lease`) -> SUCCEEDED / FAILED / CANCELLED. `outcome` supplies error,
  // artifacts and metrics_json.
  virtual absl::StatusOr<v1::Job> Finish(const Lease& lease, v1::JobState state,
                                         const v1::Job& outcome) = 0;
  // RUNNING (held by `lease`) -> QUEUED, giving back the attempt (graceful shutdown).
  virtual absl::StatusOr<v1::Job> Requeue(const Lease& lease, const std::string& reason) = 0;
  // RUNNING jobs whose lease lapsed (all RUNNING jobs when `all`) go back to QUEUED, or to
  // FAILED once they were claimed `max_attempts` times. `all` is only for start-up of an
  // exclusive store (below): a shared store's RUNNING jobs may belong to live replicas.
  virtual absl::StatusOr<Recovered> RecoverLeases(bool all, int max_attempts) = 0;
  // True for an embedded store only this process uses (SQLite under the data dir's LOCK): at
  // start-up every RUNNING job in it is an orphan of a dead process.
  virtual bool exclusive() const = 0;
  // Gives the space of deleted rows back to the filesystem where the engine does not do it by
  // itself (SQLite's incremental vacuum; PostgreSQL's autovacuum needs nothing). Called by the
  // server's collector timer.
  virtual absl::Status Compact() { return absl::OkStatus(); }
  // One quick round trip to the store, without the reconnect retries of the other calls: the
  // health service follows it (NOT_SERVING while it fails). UNAVAILABLE naming the store.
  virtual absl::Status Ping() { return absl::OkStatus(); }

  // QUEUED -> CANCELLED at once; RUNNING -> cancel requested (the worker finishes it).
  // Final jobs are returned unchanged.
  virtual absl::StatusOr<v1::Job> Cancel(const std::string& id) = 0;
  virtual absl::StatusOr<bool> CancelRequested(const std::string& id) = 0;
  // FAILED / CANCELLED -> QUEUED (attempts reset); FAILED_PRECONDITION otherwise.
  virtual absl::StatusOr<v1::Job> Retry(const std::string& id, int max_queued) = 0;
  // Final jobs only (FAILED_PRECONDITION otherwise); removes the events too.
  virtual absl::Status DeleteJob(const std::string& id) = 0;

  // Events with sequence > after, at most `limit`, in order.
  virtual absl::StatusOr<std::vector<v1::JobEvent>> ListEvents(const std::string& id, int64_t after,
                                                               int limit) = 0;

  // Volumes. CreateVolume with a used non-empty request_id returns the first volume; else, with
  // a non-empty `content_key` (VolumeContentKey, volume_catalog.h) that a stored volume of the
  // same creator has, that volume. Either way `*created` = false. Two creates of one content
  // by one creator, also concurrent ones through several replicas, make one row; another
  // creator's volume is never returned by content. The creator is the stored proto's
  // Volume.creator (set by the caller).
  virtual absl::StatusOr<v1::Volume> CreateVolume(const std::string& id, const v1::Volume& volume,
                                                  const std::string& request_id,
                                                  const std::string& content_key,
                                                  bool* created) = 0;
  virtual absl::StatusOr<v1::Volume> GetVolume(const std::string& id) = 0;
  // Newest first; `creator` non-empty: only volumes whose Volume.creator equals it.
  virtual absl::StatusOr<VolumePage> ListVolumes(const std::string& creator, int page_size,
                                                 const std::string& page_token) = 0;
  // FAILED_PRECONDITION while a QUEUED or RUNNING job reads it.
  virtual absl::Status DeleteVolume(const std::string& id) = 0;
  // True if any stored volume lists blob `sha256` (or a received DICOM instance holds it).
  virtual absl::StatusOr<bool> BlobInUse(const std::string& sha256) = 0;

  // PACS receiver state (tables dicom_instances and dicom_series in both stores). Not pure: a
  // store without them answers UNIMPLEMENTED, and the receiver refuses to start on it.
  // Inserts a received instance, keyed by (calling_ae, sop_instance_uid). The same bytes
  // (sha256) again replace the row, which moves to the end of the arrival order; other bytes
  // under a key already held are refused with ALREADY_EXISTS and nothing changes.
  virtual absl::Status PutDicomInstance(const DicomInstanceRecord& instance);
  // Every received instance not yet consumed by a job, in arrival order.
  virtual absl::StatusOr<std::vector<DicomInstanceRecord>> ListDicomInstances();
  // Sets aborted_ms of every received (not consumed) instance of `calling_ae`'s series: an
  // association that sent some of them ended without a release.
  virtual absl::Status MarkDicomSeriesAborted(const std::string& calling_ae,
                                              const std::string& series_instance_uid,
                                              int64_t aborted_ms);
  // Inserts or replaces (by receive_key) a receive's row and, in the same transaction, removes
  // the instances `consumed` (SOP Instance UIDs of series.calling_ae) from the received ones.
  virtual absl::Status PutDicomSeries(const DicomSeriesRecord& series,
                                      const std::vector<std::string>& consumed);
  // Newest first, at most `limit`; only those still followed (results_pending) when
  // `pending_only`.
  virtual absl::StatusOr<std::vector<DicomSeriesRecord>> ListDicomSeries(bool pending_only,
                                                                         int limit);
  // Removes the received instances of `calling_ae`'s series (expired or deleted) and returns
  // them; their blobs are the caller's to release.
  virtual absl::StatusOr<std::vector<DicomInstanceRecord>> RemoveDicomInstances(
      const std::string& calling_ae, const std::string& series_instance_uid);
  // The bytes of the instances from `calling_ae` still waiting (the per-sender quota).
  virtual absl::StatusOr<int64_t> DicomWaitingBytes(const std::string& calling_ae);
};

// The embedded store: one SQLite database file in WAL mode.
absl::StatusOr<std::unique_ptr<JobStore>> OpenSqliteJobStore(const std::string& path);

struct PostgresStoreOptions {
  int connections = 8;  // pooled connections; the event feed uses one more
  std::string application_name = "decima-server";  // pg_stat_activity shows it
  // How long a call waits for a lost PostgreSQL to come back before failing UNAVAILABLE.
  std::chrono::milliseconds reconnect_timeout{30000};
};

// The shared store: PostgreSQL at `dsn` (a libpq URI or key=value string). Applies the schema
// migrations (under an advisory lock, so replicas may start together) and starts the LISTEN
// thread of the event feed.
absl::StatusOr<std::unique_ptr<JobStore>> OpenPostgresJobStore(const std::string& dsn,
                                                               const PostgresStoreOptions& options);

// "jobs/{id}" -> id, INVALID_ARGUMENT naming `field` otherwise. Same for volumes and blobs.
absl::StatusOr<std::string> ParseName(const std::string& name, const std::string& collection,
                                      const std::string& field);

}  // namespace decima::server
