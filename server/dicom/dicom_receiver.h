// The PACS side of decima-server (off by default; --dicom-listen turns it on):
//
//   C-STORE in  a DCMTK storage SCP serving up to max_associations associations at once (at most
//               max_per_peer from one address; more connections are closed at once). Each
//               connection has timeout_seconds to send its whole A-ASSOCIATE-RQ (ARTIM, waited
//               for here before DCMTK reads it, so a silent connection holds nothing but its own
//               thread) and an association may stay silent between DIMSE messages as long.
//               Verification (C-ECHO) and every storage SOP class are accepted, in the
//               uncompressed and compressed transfer syntaxes the job's reader decodes; deflated
//               syntaxes are refused at negotiation (the job's reader does not inflate, and
//               inflating in the server is what a deflate bomb needs). An instance is written
//               to dicom-spool/ and the association aborted once it passes max_instance_bytes;
//               else it is stored as a blob (blob_store.h) and recorded in the job store
//               (JobStore::PutDicomInstance) before the C-STORE response says success, so an
//               acknowledged instance survives a restart. Its UIDs (and later the series check's
//               attributes) are read from its first 64 KiB only, by DCMTK up to the pixel
//               data, so a header costs bounded memory whatever lengths it declares.
//   association each accepted association gets an id (NewId, 16 hex digits), logged with the
//               peer's address and AE titles when it is accepted and when it ends; every
//               instance it brings and every receive records it (association_id), and the audit
//               records of the job a receive queued and of its results' send carry it.
//   keying      everything is kept per sender, the calling AE title (whose principal
//               "dicom:<AE>" creates the volume and job): an instance is unique per (sender,
//               SOP Instance UID), a series per (sender, SeriesInstanceUID). Another sender's
//               instances never complete, replace or claim a series; one sender's re-send of an
//               instance it holds with other bytes is refused (C-STORE 0111H) and logged, the
//               first bytes stay. Instances of a SOP class that is no slice of a volume (SEG,
//               SC, SR, ...) are refused at C-STORE time (0122H), never left waiting.
//   group       a sender's series whose newest instance is older than the quiet time is
//               checked once per set of SOP Instance UIDs and newest arrival
//               (CheckSeriesComplete): quiet alone does not mean complete (Orthanc's "stable"
//               fired after 1 of 113 instances, and an aborted send looked stable at 79).
//   job         a complete series becomes a volume and a job with the route's spec; both use
//               the request id "dicom-<sha256 of the sender and the sorted SOP Instance UIDs>"
//               (a prefix CreateJob and CreateVolume refuse to anyone else), so the same set
//               sent again by the same sender reuses the first job instead of making a second
//               one; a job or volume under that id with another creator is not reused (not
//               queued, logged). An incomplete series queues nothing: its instances wait for
//               more (a resumed send), at most --dicom-incomplete-expiry, after which they and
//               their blobs are removed. Nor does a series whose last association was aborted
//               until more arrives (the mark is stored with its instances,
//               JobStore::MarkDicomSeriesAborted). A sender's waiting bytes are capped by
//               --dicom-quota-mb (C-STORE A700 beyond).
//   history     every receive (one check of a sender's series, or its refused, expired or
//               deleted instances) is its own row (JobStore::PutDicomSeries), which the settle
//               loop advances honestly: COMPLETE -> QUEUED -> RUNNING -> SUCCEEDED / FAILED ->
//               SENT / SEND_FAILED; an earlier INCOMPLETE receive that a later one completes
//               becomes COMPLETE with its job. ListReceivedSeries
//               (decima.v1.Volumes.ListReceivedSeries) shows them; DeleteReceivedSeries
//               removes a series' waiting instances.
//   results     each receive records its route: when the route has a destination, the job's
//               DICOM artifacts (segmentation.dcm, sc-*.dcm; dicom_results.h) are sent there
//               once it SUCCEEDED (dicom_sender.h), at most 3 attempts 5 s apart, for every
//               receive that reused the job too (each sender and route gets its results).
// Associations are refused when the data dir's file system has less than min_free_mb free,
// when the called AE title is not ours, and (routes "refuse_unknown_calling_ae") when no route
// names the calling AE title. The port is bound to the --dicom-listen host only (and, with a
// loopback host, peers other than loopback are refused at association time as well).
// Thread-safety: Start/Stop from one thread; the listener, each connection and the settle loop
// run on their own threads. The connections call StoreInstance one at a time (store_mu_) and
// MarkAborted concurrently (the job store is thread-safe).
#pragma once

#include <atomic>
#include <condition_variable>
#include <filesystem>
#include <functional>
#include <list>
#include <map>
#include <memory>
#include <mutex>
#include <set>
#include <string>
#include <thread>
#include <vector>

#include "absl/base/thread_annotations.h"
#include "absl/status/statusor.h"
#include "server/access/audit_log.h"
#include "server/dicom/dicom_routes.h"
#include "server/files/blob_store.h"
#include "server/files/data_dir.h"
#include "server/files/volume_catalog.h"
#include "server/jobs/worker_pool.h"
#include "server/store/job_store.h"

namespace decima::server {

struct DicomReceiverOptions {
  std::string host = "127.0.0.1";
  int port = 11112;
  std::string aet = "DECIMA";  // our AE title: the called AE title we answer to
  // A series is checked once no instance came for this long. 1 s: a sender's instances
  // follow each other within milliseconds, completeness is judged by CheckSeriesComplete (and
  // an aborted association never queues), so the quiet time only has to outlast the gaps of a
  // send; 3 s made the Orthanc -> Decima -> SEG + SC loop miss "job time + 3 s".
  double quiet_seconds = 1;
  int64_t min_free_mb = 1024;  // refuse associations / instances below this much free disk
  int max_queued = 1000;       // as --max-queued
  double poll_seconds = 0.2;   // settle loop period
  // Associations served at once, and from one peer address (connections beyond are closed as
  // soon as they are accepted): one silent or slow peer cannot hold the port for the others.
  int max_associations = 32;
  int max_per_peer = 8;
  // Seconds a connection may take to send its association request (the ARTIM timer of PS3.8
  // 9.1.5) and an association may stay silent between messages. 30: a sender pauses for
  // milliseconds between instances; DCMTK's own default was 60, and a silent peer held the
  // port for that long.
  int timeout_seconds = 30;
  // Largest instance accepted by C-STORE (as --max-upload-mb for uploads); the association is
  // aborted when a dataset grows past it.
  int64_t max_instance_bytes = int64_t{2048} << 20;
  // A series whose newest instance is older than this and still waits (incomplete, aborted,
  // not queued) is removed with its blobs; 0 never. A day: a resumed send comes back within
  // hours, and junk must not hold the disk for longer.
  double incomplete_expiry_seconds = 86400;
  // Waiting (not yet consumed) bytes per calling AE title; an instance beyond is refused. 0
  // no limit. 10 GiB: ten large CT studies in flight from one sender.
  int64_t quota_mb = 10240;
  DicomRoutes routes;
  // Jobs queued from received series and the sending of their results (null: not audited).
  std::shared_ptr<const AuditLog> audit;
};

// Checks that `files` (one series) form a volume: each a single-frame image with
// ImagePositionPatient, ImageOrientationPatient, PixelSpacing, Rows and Columns; one
// orientation, one size, one pixel spacing; at least 2 slices; no fewer instances than an
// ImagesInAcquisition (0020,1002) that is present says; no duplicate position; every
// slice on the normal through the first (no tilt); and consecutive gaps along the normal equal
// to the smallest gap within 1% + 0.01 mm (a missing slice shows as a double gap).
// INVALID_ARGUMENT saying what is wrong, e.g. "1 slice missing between z=22 and z=26 mm (gap
// 4 mm, expected 2 mm); 112 instances".
absl::Status CheckSeriesComplete(const std::vector<std::filesystem::path>& files);

// The principal a received series' volume and job are created by: "dicom:<calling AE title>".
// A tokens-file submitter of that name sees them (and only them, of the received ones).
std::string DicomOwner(const std::string& calling_ae);

// CreateJob and CreateVolume: INVALID_ARGUMENT for a request id with the prefix "dicom-", which
// is the receiver's (its jobs and volumes are found again by it); OK otherwise.
absl::Status RefuseReceiverRequestId(const std::string& request_id);

struct ReceivedSeriesPage {
  std::vector<v1::ReceivedSeries> series;
  std::string next_page_token;
};

// decima.v1.Volumes.ListReceivedSeries: the receives from the job store (the newest 1000 rows,
// and a RECEIVING entry for each sender's series whose waiting instances are not checked yet),
// newest arrival first. `owner` non-empty: only the receives it owns. INVALID_ARGUMENT for a
// page token this did not return.
absl::StatusOr<ReceivedSeriesPage> ListReceivedSeries(JobStore* store, const std::string& owner,
                                                      int page_size, const std::string& page_token);

struct RemovedSeries {
  int instances = 0;
  int64_t freed_bytes = 0;  // blobs no volume or other instance held any more
};

// decima.v1.Volumes.DeleteReceivedSeries: removes the waiting instances of `series_uid` from
// `calling_ae` ("" every sender) and frees their blobs; the history gets a DELETED row whose
// reason names `deleted_by`. `may_delete(owner)` says whether the caller may delete a sender's
// (owner "dicom:<AE>"); senders it refuses are skipped. INVALID_ARGUMENT for a malformed UID or
// AE title, NOT_FOUND when nothing of it waits, may_delete's refusal when it refused every
// sender that had some.
absl::StatusOr<RemovedSeries> DeleteReceivedSeries(
    JobStore* store, BlobStore* blobs, const std::string& series_uid, const std::string& calling_ae,
    const std::string& deleted_by,
    const std::function<absl::Status(const std::string& owner)>& may_delete);

class DicomReceiver {
 public:
  DicomReceiver(DicomReceiverOptions options, const DataDir* data_dir, JobStore* store,
                BlobStore* blobs, VolumeCatalog* catalog, WorkerPool* pool);
  ~DicomReceiver();

  // Opens the port and starts the SCP and the settle loop. UNIMPLEMENTED if the job store
  // keeps no receiver state; UNAVAILABLE if the port cannot be opened.
  absl::Status Start();
  // Stops accepting, breaks off the open associations (their connections are shut down) and
  // joins every thread; returns within about a second.
  void Stop();
  // The port bound by Start (options().port, or the one the system chose for port 0).
  int port() const { return bound_port_; }

  // Called by an association's thread (serialized by store_mu_) for each received file (spool
  // path): stores it (blob + store row). Returns the DIMSE status for the C-STORE response: 0
  // stored; 0122H a SOP class that is no slice of a volume (recorded as a REFUSED receive); 0111H
  // this sender's SOP instance again with other bytes (refused, logged, recorded); A700 no disk or
  // over the sender's quota; C000 not understood. `*series_uid` receives the instance's series when
  // stored. `association_id`: the association that brought it ("" for none, as in tests).
  uint16_t StoreInstance(const std::filesystem::path& file, const std::string& calling_ae,
                         const std::string& called_ae, std::string* series_uid,
                         const std::string& association_id = "");
  // Called by the SCP thread when an association that brought these series ended without a
  // release: they are not queued until an instance newer than the abort arrives (the mark is
  // stored with their instances).
  void MarkAborted(const std::string& calling_ae, const std::set<std::string>& series);
  // True when the data dir has at least min_free_mb free.
  bool DiskSpaceAllows(std::string* why) const;
  const DicomReceiverOptions& options() const { return options_; }
  bool stopping() const { return stop_.load(); }
  std::filesystem::path spool() const;

 private:
  friend class StorageScp;
  void SettleLoop();
  void AcceptLoop();
  void ServeConnection(int fd, const std::string& peer);
  void SettleSeries(const std::string& series_uid,
                    const std::vector<DicomInstanceRecord>& instances, const std::string& key);
  // Advances the receives still followed: their job's state, then the send of its results.
  void FollowReceives();
  // Records a refused instance in its sender's REFUSED receive: one per association, series
  // and kind of refusal (without an association, one per sender, series and kind in this
  // process).
  void RecordRefused(const std::string& kind, const std::string& series_uid,
                     const std::string& calling_ae, const std::string& called_ae,
                     const std::string& reason, const std::string& association_id);
  // Forgets the refusal counts of an association that ended (its rows stay in the store).
  void EndAssociation(const std::string& association_id);

  const DicomReceiverOptions options_;
  const DataDir* data_dir_;
  JobStore* store_;
  BlobStore* blobs_;
  VolumeCatalog* catalog_;
  WorkerPool* pool_;

  std::atomic<bool> stop_{false};
  std::thread accept_thread_, settle_thread_;
  int listen_fd_ = -1;
  int bound_port_ = 0;
  // One per accepted connection: its socket (-1 once DCMTK is about to close it) and thread.
  struct Connection {
    int fd = -1;
    std::string peer;
    std::thread thread;
    bool done = false;
  };
  std::mutex conn_mu_;
  std::list<Connection> connections_ ABSL_GUARDED_BY(conn_mu_);
  // Associations run concurrently; storing an instance (blob copy + store row) is serialized,
  // as it was with one association at a time.
  std::mutex store_mu_;
  std::mutex mu_;
  std::condition_variable cv_;
  bool wake_ ABSL_GUARDED_BY(mu_) = false;
  // Settle-loop only: instance sets already checked (pruned to those still pending), send
  // attempts per job.
  std::map<std::string, int64_t> checked_;    // instance set -> its newest arrival when checked
  std::map<std::string, int> send_attempts_;  // by receive key
  std::map<std::string, int64_t> next_send_ms_;
  std::unique_ptr<class ScpNetwork> net_;
  struct Refused {
    int count = 0;
    int64_t first_ms = 0;
  };
  std::map<std::string, Refused> refused_ ABSL_GUARDED_BY(mu_);  // by receive key
  const int64_t started_ms_;
};

}  // namespace decima::server
