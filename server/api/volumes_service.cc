// decima.v1.Volumes: volumes made of uploaded blobs (volume_catalog.h), and the series the
// DICOM receiver got (dicom_receiver.h), which become volumes.
#include "absl/strings/str_cat.h"
#include "decima/v1/volumes.grpc.pb.h"
#include "server/api/grpc_util.h"
#include "server/api/handler.h"
#include "server/api/service.h"
#include "server/dicom/dicom_receiver.h"

namespace decima::server {
namespace {

class VolumesService final : public v1::Volumes::Service {
 public:
  explicit VolumesService(const ServiceDeps& d) : d_(d) {}

  grpc::Status CreateVolume(grpc::ServerContext* ctx, const v1::CreateVolumeRequest* req,
                            v1::Volume* resp) override {
    return Audited(d_, ctx, "CreateVolume", "",
                   [&](const Principal& caller, std::string& resource) {
                     grpc::Status st = DoCreateVolume(ctx, caller, *req, resp);
                     if (st.ok()) resource = resp->name();
                     return st;
                   });
  }

  grpc::Status DoCreateVolume(grpc::ServerContext* ctx, const Principal& caller,
                              const v1::CreateVolumeRequest& req, v1::Volume* resp) {
    if (auto may = CallGuard::MayCreate(caller, "volumes"); !may.ok()) return may;
    v1::ErrorDetail detail;
    if (auto st = RefuseReceiverRequestId(req.request_id()); !st.ok()) {
      detail.set_field("request_id");
      return Fail(ctx, st, detail);
    }
    auto vol = d_.volumes->Create(req, caller.name, &detail);
    if (!vol.ok())
      return detail.field().empty() ? ToGrpc(vol.status()) : Fail(ctx, vol.status(), detail);
    // A request_id another principal used returns that principal's volume: not to be revealed.
    if (auto may = CallGuard::MayRead(caller, vol->creator(), "request_id " + req.request_id());
        !may.ok()) {
      return may;
    }
    *resp = std::move(*vol);
    return grpc::Status::OK;
  }

  grpc::Status GetVolume(grpc::ServerContext* ctx, const v1::GetVolumeRequest* req,
                         v1::Volume* resp) override {
    return Guarded(d_, ctx, [&](const Principal& caller) -> grpc::Status {
      auto id = ParseName(req->name(), "volumes", "name");
      if (!id.ok()) return ToGrpc(id.status());
      auto v = d_.jobs->GetVolume(*id);
      if (!v.ok()) return ToGrpc(v.status());
      if (auto may = CallGuard::MayRead(caller, v->creator(), req->name()); !may.ok()) return may;
      *resp = std::move(*v);
      return grpc::Status::OK;
    });
  }

  grpc::Status ListVolumes(grpc::ServerContext* ctx, const v1::ListVolumesRequest* req,
                           v1::ListVolumesResponse* resp) override {
    return Guarded(d_, ctx, [&](const Principal& caller) -> grpc::Status {
      if (req->page_size() < 0) return InvalidField(ctx, "page_size", "must be >= 0");
      auto page =
          d_.jobs->ListVolumes(CallGuard::ListFilter(caller), req->page_size(), req->page_token());
      if (!page.ok()) return ToGrpc(page.status());
      for (auto& v : page->volumes) *resp->add_volumes() = std::move(v);
      resp->set_next_page_token(page->next_page_token);
      return grpc::Status::OK;
    });
  }

  // Readers and admins see every received series; a submitter those it owns (the principal
  // "dicom:<calling AE>" that also creates their volumes and jobs), as with ListVolumes.
  grpc::Status ListReceivedSeries(grpc::ServerContext* ctx,
                                  const v1::ListReceivedSeriesRequest* req,
                                  v1::ListReceivedSeriesResponse* resp) override {
    return Guarded(d_, ctx, [&](const Principal& caller) -> grpc::Status {
      if (req->page_size() < 0) return InvalidField(ctx, "page_size", "must be >= 0");
      auto page = server::ListReceivedSeries(d_.jobs, CallGuard::ListFilter(caller),
                                             req->page_size(), req->page_token());
      if (!page.ok()) return ToGrpc(page.status());
      for (auto& r : page->series) *resp->add_received_series() = std::move(r);
      resp->set_next_page_token(page->next_page_token);
      return grpc::Status::OK;
    });
  }

  grpc::Status DeleteReceivedSeries(grpc::ServerContext* ctx,
                                    const v1::DeleteReceivedSeriesRequest* req,
                                    v1::DeleteReceivedSeriesResponse* resp) override {
    const std::string what = absl::StrCat("received series ", req->series_instance_uid());
    return Audited(d_, ctx, "DeleteReceivedSeries", what,
                   [&](const Principal& caller, std::string&) -> grpc::Status {
                     // A reader may delete nothing, whatever waits (answered before NOT_FOUND
                     // could tell it what does); per sender below, whoever may change what it
                     // creates (its owner "dicom:<AE>", or an admin).
                     if (auto may = CallGuard::MayWrite(caller, caller.name, what); !may.ok()) {
                       return may;
                     }
                     auto removed = server::DeleteReceivedSeries(
                         d_.jobs, d_.blobs, req->series_instance_uid(), req->calling_ae(),
                         caller.name, [&](const std::string& owner) {
                           grpc::Status may = CallGuard::MayWrite(caller, owner, what);
                           return absl::Status(static_cast<absl::StatusCode>(may.error_code()),
                                               may.error_message());
                         });
                     if (!removed.ok()) return ToGrpc(removed.status());
                     resp->set_deleted_instances(removed->instances);
                     resp->set_freed_bytes(removed->freed_bytes);
                     return grpc::Status::OK;
                   });
  }

  grpc::Status DeleteVolume(grpc::ServerContext* ctx, const v1::DeleteVolumeRequest* req,
                            v1::DeleteVolumeResponse*) override {
    return Audited(
        d_, ctx, "DeleteVolume", req->name(),
        [&](const Principal& caller, std::string&) { return DoDeleteVolume(caller, *req); });
  }

  grpc::Status DoDeleteVolume(const Principal& caller, const v1::DeleteVolumeRequest& req) {
    auto id = ParseName(req.name(), "volumes", "name");
    if (!id.ok()) return ToGrpc(id.status());
    auto v = d_.jobs->GetVolume(*id);
    if (!v.ok()) return ToGrpc(v.status());
    if (auto may = CallGuard::MayWrite(caller, v->creator(), req.name()); !may.ok()) return may;
    return ToGrpc(d_.volumes->Delete(*id));
  }

 private:
  const ServiceDeps d_;
};

}  // namespace

std::unique_ptr<grpc::Service> MakeVolumesService(const ServiceDeps& deps) {
  return std::make_unique<VolumesService>(deps);
}

}  // namespace decima::server
