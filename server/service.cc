#include "server/service.h"

namespace decima::server {

Services::Services(ServiceOptions options, JobStore* jobs, BlobStore* blobs, EventBus* bus,
                   WorkerPool* pool)
    : options_(std::move(options)),
      guard_(options_.identities),
      audit_(options_.audit ? options_.audit : std::make_shared<AuditLog>()) {
  const ServiceDeps deps{&options_, jobs, blobs, bus, pool, &guard_, audit_.get()};
  uploads_ = MakeUploadsService(deps);
  volumes_ = MakeVolumesService(deps);
  jobs_ = MakeJobsService(deps);
  artifacts_ = MakeArtifactsService(deps);
}

}  // namespace decima::server
