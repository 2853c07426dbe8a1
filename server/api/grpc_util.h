// The edge between absl and gRPC, shared by the service files: status conversion keeping code
// and message, and the structured error detail in the trailing metadata "decima-error-bin"
// (decima.v1.ErrorDetail). Resource ids are in server/util/ids.h.
#pragma once

#include <grpcpp/grpcpp.h>

#include <string>

#include "absl/status/status.h"
#include "decima/v1/errors.pb.h"

namespace decima::server {

// absl::Status -> grpc::Status with the same code and message.
grpc::Status ToGrpc(const absl::Status& s);

// `s` with `detail` attached to the call's trailing metadata.
grpc::Status Fail(grpc::ServerContext* ctx, const absl::Status& s, const v1::ErrorDetail& detail);

// INVALID_ARGUMENT "<field>: <message>" with ErrorDetail.field set.
grpc::Status InvalidField(grpc::ServerContext* ctx, const std::string& field,
                          const std::string& message);

}  // namespace decima::server
