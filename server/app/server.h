// A running decima-server: its parts, started in order by Server::Start (lock, identities, TLS,
// audit, job store, blobs, event bus, worker pool, services, collector, gRPC, health, DICOM,
// lease reaper) and stopped by Drain. main() is ParseFlags -> Start -> WaitForStopSignal -> Drain.
#pragma once

#include <signal.h>

#include <atomic>
#include <filesystem>
#include <memory>
#include <string>

#include <grpcpp/grpcpp.h>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "server/access/tls_files.h"
#include "server/api/service.h"
#include "server/app/server_options.h"
#include "server/dicom/dicom_receiver.h"
#include "server/jobs/lease_reaper.h"
#include "server/util/periodic_task.h"

namespace decima::server {

class Server {
 public:
  // Starts every part, or returns the first failure, whose message is the log line that names
  // the flag or file (main exits 1). Blocks SIGTERM and SIGINT in every thread it starts; the
  // caller waits for them with WaitForStopSignal.
  static absl::StatusOr<std::unique_ptr<Server>> Start(const ServerOptions& options);

  Server(const Server&) = delete;
  Server& operator=(const Server&) = delete;
  // The parts go in the reverse order of their start, as the members are declared.
  ~Server() = default;

  // Blocks until SIGTERM or SIGINT; returns which.
  int WaitForStopSignal();
  // Health NOT_SERVING, new calls UNAVAILABLE, no new DICOM series; running jobs get
  // --drain-seconds, then are requeued; the store is compacted and closed.
  void Drain(int signal);

 private:
  explicit Server(const ServerOptions& options) : options_(options) {}

  absl::Status ConfigureDicom();
  void BlockStopSignals();
  absl::Status LockDataDir();
  absl::Status LoadIdentities();
  absl::Status StartTls();
  absl::Status OpenAudit();
  absl::Status OpenStores();
  absl::Status RecoverJobs();
  void StartServices();
  absl::Status StartGrpc();
  void WatchStoreHealth();
  absl::Status StartDicom();
  void AnnounceListening();

  const ServerOptions options_;
  DicomReceiverOptions dicom_;
  sigset_t stop_signals_;
  std::filesystem::path data_;
  std::string store_uri_;  // --store, or --store-file's content
  bool postgres_ = false;
  int lock_fd_ = -1;  // held for the life of the process
  std::string owner_;
  Identities identities_;
  bool callers_identified_ = false;
  std::unique_ptr<TlsFileGuard> tls_guard_;
  std::shared_ptr<AuditLog> audit_;
  std::unique_ptr<JobStore> store_;
  std::unique_ptr<LocalBlobStore> blobs_;
  EventBus bus_;
  // The worker pool the store's listener wakes; null before it exists and from the drain on.
  std::atomic<WorkerPool*> wake_pool_{nullptr};
  WorkerPoolOptions pool_options_;
  std::unique_ptr<WorkerPool> pool_;
  ServiceOptions service_options_;
  std::unique_ptr<Services> services_;
  std::unique_ptr<PeriodicTask> collector_;
  std::unique_ptr<grpc::Server> grpc_;
  int port_ = 0;
  std::atomic<bool> store_ok_{true}, draining_{false};
  std::unique_ptr<PeriodicTask> store_health_;
  std::unique_ptr<DicomReceiver> receiver_;
  std::unique_ptr<LeaseReaper> reaper_;
};

}  // namespace decima::server
