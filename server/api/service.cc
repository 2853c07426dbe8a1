#include "server/api/service.h"

#include "decima/v1/artifacts.grpc.pb.h"
#include "decima/v1/jobs.grpc.pb.h"
#include "decima/v1/uploads.grpc.pb.h"
#include "decima/v1/volumes.grpc.pb.h"
#include "grpc/reflection/v1alpha/reflection.grpc.pb.h"
#include "spdlog/spdlog.h"

namespace decima::server {

Services::Services(ServiceOptions options, JobStore* jobs, BlobStore* blobs, EventBus* bus,
                   WorkerPool* pool)
    : options_(std::move(options)),
      store_(jobs),
      guard_(options_.identities),
      audit_(options_.audit ? options_.audit : std::make_shared<AuditLog>()),
      disk_(options_.data_dir.root(), options_.disk_reserve_bytes),
      catalog_(&options_.data_dir, jobs, blobs, &disk_, options_.blob_sweep) {
  disk_.Refill();
  const ServiceDeps deps{&options_, jobs,         blobs,  bus,      pool,
                         &guard_,   audit_.get(), &disk_, &catalog_};
  uploads_ = MakeUploadsService(deps);
  volumes_ = MakeVolumesService(deps);
  jobs_ = MakeJobsService(deps);
  artifacts_ = MakeArtifactsService(deps);
  reflection_ = MakeReflectionService(
      &guard_,
      {v1::Uploads::service_full_name(), v1::Volumes::service_full_name(),
       v1::Jobs::service_full_name(), v1::Artifacts::service_full_name(), "grpc.health.v1.Health",
       grpc::reflection::v1alpha::ServerReflection::service_full_name()});
}

BlobSweepStats Services::CollectGarbage() {
  BlobSweepStats stats = catalog_.CollectGarbage();
  if (absl::Status st = store_->Compact(); !st.ok())
    spdlog::warn("compacting the job store: {}", st.ToString());
  disk_.Refill();
  return stats;
}

}  // namespace decima::server
