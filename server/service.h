// The gRPC services of decima.v1 (Uploads, Volumes, Jobs, Artifacts) over one job store, one
// blob store, the event bus and the worker pool. Handlers validate, call one store or pool
// operation, and convert absl::Status to grpc::Status at the edge, keeping code and message.
// Every handler starts with the same guard: the bearer token (when configured) and the drain
// state. The standard health and reflection services are registered beside these (server.cc).
#pragma once

#include <atomic>
#include <filesystem>
#include <memory>
#include <string>

#include "decima/v1/artifacts.grpc.pb.h"
#include "decima/v1/jobs.grpc.pb.h"
#include "decima/v1/uploads.grpc.pb.h"
#include "decima/v1/volumes.grpc.pb.h"
#include "server/blob_store.h"
#include "server/data_dir.h"
#include "server/event_bus.h"
#include "server/job_store.h"
#include "server/worker_pool.h"

namespace decima::server {

struct ServiceOptions {
  DataDir data_dir{""};
  std::string token;  // empty: no authentication
  int64_t max_upload_bytes = int64_t{2} << 30;
  int max_queued = 1000;
  bool allow_faults = false;    // read the test fault seam (faults.h), tests only
  int64_t heartbeat_ms = 5000;  // WatchJob heartbeat period
};

inline constexpr size_t kMaxChunkBytes = size_t{1} << 20;

class Services {
 public:
  Services(ServiceOptions options, JobStore* jobs, BlobStore* blobs, EventBus* bus,
           WorkerPool* pool);
  ~Services();

  // Refuse new calls with UNAVAILABLE and end watch streams.
  void StartDraining();
  bool draining() const { return draining_.load(); }

  grpc::Service* uploads();
  grpc::Service* volumes();
  grpc::Service* jobs();
  grpc::Service* artifacts();

  // The common guard: UNAUTHENTICATED without the right bearer token, UNAVAILABLE while
  // draining. Public for tests.
  grpc::Status Guard(grpc::ServerContext* ctx) const;

  class UploadsImpl;
  class VolumesImpl;
  class JobsImpl;
  class ArtifactsImpl;

 private:
  ServiceOptions options_;
  JobStore* jobs_store_;
  BlobStore* blob_store_;
  EventBus* bus_;
  WorkerPool* pool_;
  std::atomic<bool> draining_{false};
  std::unique_ptr<UploadsImpl> uploads_;
  std::unique_ptr<VolumesImpl> volumes_;
  std::unique_ptr<JobsImpl> jobs_;
  std::unique_ptr<ArtifactsImpl> artifacts_;
};

// absl::Status -> grpc::Status with the same code and message.
grpc::Status ToGrpc(const absl::Status& s);

// A random resource id: 16 lower-case hex characters.
std::string NewId();

}  // namespace decima::server
