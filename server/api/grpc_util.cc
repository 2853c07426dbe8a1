#include "server/api/grpc_util.h"

#include "absl/strings/str_cat.h"

namespace decima::server {

grpc::Status ToGrpc(const absl::Status& s) {
  if (s.ok()) return grpc::Status::OK;
  return grpc::Status(static_cast<grpc::StatusCode>(s.code()), std::string(s.message()));
}

grpc::Status Fail(grpc::ServerContext* ctx, const absl::Status& s, const v1::ErrorDetail& d) {
  ctx->AddTrailingMetadata("decima-error-bin", d.SerializeAsString());
  return ToGrpc(s);
}

grpc::Status InvalidField(grpc::ServerContext* ctx, const std::string& field,
                          const std::string& message) {
  v1::ErrorDetail d;
  d.set_field(field);
  return Fail(ctx, absl::InvalidArgumentError(absl::StrCat(field, ": ", message)), d);
}

}  // namespace decima::server
