#include "server/grpc_util.h"

#include <random>

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

std::string NewId() {
  thread_local std::mt19937_64 rng([] {
    std::random_device rd;
    std::seed_seq seq{rd(), rd(), rd(), rd()};
    return std::mt19937_64(seq);
  }());
  static const char kHex[] = "0123456789abcdef";
  const uint64_t v = rng();
  std::string id(16, '0');
  for (int i = 0; i < 16; ++i) id[i] = kHex[(v >> (4 * i)) & 15];
  return id;
}

}  // namespace decima::server
