// The one check in front of every decima.v1 call: who is calling (a bearer token from the tokens
// file, compared by its sha256, or the client certificate under mutual TLS), what that caller may
// do (its role, and for a submitter the creator of the job or volume), and the drain state.
// gRPC 1.51's server interceptors cannot end a call with a status, and an AuthMetadataProcessor
// needs TLS credentials (auth must hold without TLS too), so every handler's first line is
// `guard.Check(ctx, &caller)` and every handler that touches a stored resource asks
// `guard.MayRead` / `MayWrite` with its creator; the rules themselves live here only.
// Server reflection is behind it too (reflection_service.cc); the health service is not (probes
// call it without credentials).
// Thread-safety: Check and May* from any thread; StartDraining once.
#pragma once

#include <grpcpp/grpcpp.h>

#include <atomic>
#include <optional>
#include <string>
#include <vector>

#include "absl/status/statusor.h"

namespace decima::server {

// submitter: creates uploads, volumes and jobs and reads and acts on its own only;
// reader: reads everything, changes nothing; admin: everything.
enum class Role { kSubmitter, kReader, kAdmin };
const char* RoleName(Role role);

struct Principal {
  std::string name;  // tokens file name, or the client certificate's subject common name
  Role role = Role::kAdmin;
};

// The identities a server knows. Tokens file, one entry a line ('#' comments, blank lines):
//   token <sha256 hex of the token> <name> <role>
//   cert <certificate subject common name> <role>
// Names are unique; a `cert` line gives a client certificate's CN a role (a CN without one is a
// submitter). The token itself is never stored: `printf %s "$T" | sha256sum`.
class Identities {
 public:
  // No authentication: every caller is the admin "anonymous" (a server without a token file and
  // without --tls-client-ca, as before identities).
  Identities() = default;
  // The single-token file of before: one admin principal named "admin".
  static Identities SingleToken(const std::string& token);
  // Parses a tokens file; INVALID_ARGUMENT naming the file, line and what was expected.
  static absl::StatusOr<Identities> Parse(const std::string& text, const std::string& file);

  // Whether callers must identify themselves (tokens configured or client certificates needed).
  bool required() const { return required_; }
  void RequireClientCertificates() { required_ = true; }

  // The principal of `token` (constant-time comparison of digests), or nullopt.
  std::optional<Principal> ForToken(const std::string& token) const;
  // The principal of a verified client certificate with common name `cn`.
  Principal ForCertificate(const std::string& cn) const;
  size_t size() const { return tokens_.size() + certs_.size(); }

 private:
  struct TokenEntry {
    std::string sha256;  // 32 raw bytes
    Principal principal;
  };
  std::vector<TokenEntry> tokens_;
  std::vector<Principal> certs_;
  bool required_ = false;
};

class CallGuard {
 public:
  explicit CallGuard(Identities identities) : identities_(std::move(identities)) {}

  // UNAUTHENTICATED without a known bearer token ("authorization: Bearer <token>") or verified
  // client certificate when identities are required, UNAVAILABLE while draining, else OK with
  // the caller in *caller.
  grpc::Status Check(grpc::ServerContext* ctx, Principal* caller) const;

  // Reading a job or volume created by `creator` (`what` names it in the message):
  // PERMISSION_DENIED for a submitter and someone else's resource.
  static grpc::Status MayRead(const Principal& caller, const std::string& creator,
                              const std::string& what);
  // Changing it (cancel, retry, delete): also PERMISSION_DENIED for a reader.
  static grpc::Status MayWrite(const Principal& caller, const std::string& creator,
                               const std::string& what);
  // Creating uploads, volumes and jobs: PERMISSION_DENIED for a reader.
  static grpc::Status MayCreate(const Principal& caller, const std::string& what);
  // The creator filter of a listing: the caller's name for a submitter, "" (all) otherwise.
  static std::string ListFilter(const Principal& caller);

  void StartDraining() { draining_.store(true); }
  bool draining() const { return draining_.load(); }

 private:
  const Identities identities_;
  std::atomic<bool> draining_{false};
};

}  // namespace decima::server
