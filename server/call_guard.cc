#include "server/call_guard.h"

#include <openssl/crypto.h>

namespace decima::server {

grpc::Status CallGuard::Check(grpc::ServerContext* ctx) const {
  if (!token_.empty()) {
    const auto& md = ctx->client_metadata();
    auto it = md.find("authorization");
    const std::string want = "Bearer " + token_;
    const bool ok = it != md.end() && it->second.size() == want.size() &&
                    CRYPTO_memcmp(it->second.data(), want.data(), want.size()) == 0;
    if (!ok) {
      return grpc::Status(grpc::StatusCode::UNAUTHENTICATED,
                          it == md.end() ? "missing bearer token (metadata 'authorization')"
                                         : "wrong bearer token");
    }
  }
  if (draining()) {
    return grpc::Status(grpc::StatusCode::UNAVAILABLE,
                        "the server is shutting down; retry after it restarts");
  }
  return grpc::Status::OK;
}

}  // namespace decima::server
