// The gRPC services of decima.v1, one file each: uploads_service.cc, volumes_service.cc,
// jobs_service.cc, artifacts_service.cc. Handlers are adapters: check the call (CallGuard: who,
// may they, drain; AuditLog for state changes), parse names, call one domain function
// (VolumeCatalog, SubmitJob, WatchLoop, OpenArtifact, the stores), and convert absl::Status to
// grpc::Status keeping code and message (grpc_util.h). The standard health and reflection services
// are registered beside these (server_main.cc).
#pragma once

#include <grpcpp/grpcpp.h>
#include <grpcpp/impl/service_type.h>

#include <cstdint>
#include <memory>
#include <string>

#include "server/access/audit_log.h"
#include "server/access/call_guard.h"
#include "server/files/blob_store.h"
#include "server/files/data_dir.h"
#include "server/files/disk_space.h"
#include "server/files/volume_catalog.h"
#include "server/jobs/worker_pool.h"
#include "server/store/event_bus.h"
#include "server/store/job_store.h"

namespace decima::server {

struct ServiceOptions {
  DataDir data_dir{""};
  Identities identities;            // who may call (default: anyone, as admin)
  std::shared_ptr<AuditLog> audit;  // null: no audit log
  int64_t max_upload_bytes = int64_t{2} << 30;
  int max_queued = 1000;
  bool allow_faults = false;    // read the test fault seam (faults.h), tests only
  int64_t heartbeat_ms = 5000;  // WatchJob heartbeat period
  BlobSweepPolicy blob_sweep;   // upload claims and partial-upload expiry (blob_store.h)
  int64_t disk_reserve_bytes = int64_t{64} << 20;  // disk_space.h; 0 = none
  int64_t job_memory_cap_bytes = 0;  // a job whose estimate is above is refused; 0 = no check
};

inline constexpr size_t kMaxChunkBytes = size_t{1} << 20;

// What the services share; all pointers outlive the services.
struct ServiceDeps {
  const ServiceOptions* options;
  JobStore* jobs;
  BlobStore* blobs;
  EventBus* bus;
  WorkerPool* pool;
  const CallGuard* guard;
  const AuditLog* audit;  // never null (a disabled log when none is configured)
  DiskSpace* disk;
  VolumeCatalog* volumes;
};

std::unique_ptr<grpc::Service> MakeUploadsService(const ServiceDeps& deps);
std::unique_ptr<grpc::Service> MakeVolumesService(const ServiceDeps& deps);
std::unique_ptr<grpc::Service> MakeJobsService(const ServiceDeps& deps);
std::unique_ptr<grpc::Service> MakeArtifactsService(const ServiceDeps& deps);
// grpc.reflection.v1alpha for the callers `guard` admits, listing `service_names`.
std::unique_ptr<grpc::Service> MakeReflectionService(const CallGuard* guard,
                                                     std::vector<std::string> service_names);

// The four services over one set of stores, with their guard.
class Services {
 public:
  Services(ServiceOptions options, JobStore* jobs, BlobStore* blobs, EventBus* bus,
           WorkerPool* pool);

  // Refuse new calls with UNAVAILABLE and end watch streams.
  void StartDraining() { guard_.StartDraining(); }
  bool draining() const { return guard_.draining(); }

  grpc::Service* uploads() { return uploads_.get(); }
  grpc::Service* volumes() { return volumes_.get(); }
  grpc::Service* jobs() { return jobs_.get(); }
  grpc::Service* artifacts() { return artifacts_.get(); }
  // Server reflection behind the same caller check (decima-server registers it; the standard
  // health service stays open for probes).
  grpc::Service* reflection() { return reflection_.get(); }

  // One collector pass: blobs nobody holds and abandoned partial uploads are removed, the job
  // store gives back deleted rows' space, the disk reserve is allocated again if there is room.
  // Called by the server's collector timer.
  BlobSweepStats CollectGarbage();
  DiskSpace& disk() { return disk_; }
  // The volume catalog the services use (the DICOM receiver creates its volumes through it).
  VolumeCatalog* catalog() { return &catalog_; }

 private:
  const ServiceOptions options_;
  JobStore* store_;
  CallGuard guard_;
  std::shared_ptr<AuditLog> audit_;
  DiskSpace disk_;
  VolumeCatalog catalog_;
  std::unique_ptr<grpc::Service> uploads_, volumes_, jobs_, artifacts_, reflection_;
};

}  // namespace decima::server
