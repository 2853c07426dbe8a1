#include "server/access/call_guard.h"

#include <grpc/grpc_security_constants.h>
#include <openssl/crypto.h>
#include <openssl/sha.h>

#include <set>

#include "absl/strings/ascii.h"
#include "absl/strings/escaping.h"
#include "absl/strings/match.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_split.h"
#include "server/util/sha256.h"

namespace decima::server {
namespace {

std::string RawSha256(const std::string& s) {
  unsigned char d[SHA256_DIGEST_LENGTH];
  SHA256(reinterpret_cast<const unsigned char*>(s.data()), s.size(), d);
  return std::string(reinterpret_cast<const char*>(d), sizeof d);
}

bool ParseRole(const std::string& s, Role* role) {
  if (s == "submitter")
    *role = Role::kSubmitter;
  else if (s == "reader")
    *role = Role::kReader;
  else if (s == "admin")
    *role = Role::kAdmin;
  else
    return false;
  return true;
}

grpc::Status Denied(const Principal& caller, const std::string& message) {
  return grpc::Status(grpc::StatusCode::PERMISSION_DENIED,
                      absl::StrCat(caller.name, " (", RoleName(caller.role), ") ", message));
}

}  // namespace

const char* RoleName(Role role) {
  switch (role) {
    case Role::kSubmitter:
      return "submitter";
    case Role::kReader:
      return "reader";
    case Role::kAdmin:
      return "admin";
  }
  return "?";
}

Identities Identities::SingleToken(const std::string& token) {
  Identities ids;
  ids.tokens_.push_back({RawSha256(token), Principal{"admin", Role::kAdmin}});
  ids.required_ = true;
  return ids;
}

absl::StatusOr<Identities> Identities::Parse(const std::string& text, const std::string& file) {
  Identities ids;
  std::set<std::string> names;
  int line_no = 0;
  for (absl::string_view raw : absl::StrSplit(text, '\n')) {
    ++line_no;
    absl::string_view line = absl::StripAsciiWhitespace(raw);
    if (line.empty() || line[0] == '#') continue;
    std::vector<std::string> f = absl::StrSplit(line, absl::ByAnyChar(" \t"), absl::SkipEmpty());
    auto bad = [&](const std::string& what) {
      return absl::InvalidArgumentError(
          absl::StrCat("--tokens-file ", file, " line ", line_no, ": ", what));
    };
    Principal p;
    if (f[0] == "token") {
      if (f.size() != 4) return bad("expected 'token <sha256 hex> <name> <role>'");
      if (!IsSha256Hex(f[1])) {
        return bad("expected the token's sha256 as 64 lower-case hex digits (never the token)");
      }
      p.name = f[2];
      if (!ParseRole(f[3], &p.role)) {
        return bad(absl::StrCat("role '", f[3], "': expected submitter, reader or admin"));
      }
      ids.tokens_.push_back({absl::HexStringToBytes(f[1]), p});
    } else if (f[0] == "cert") {
      if (f.size() != 3) return bad("expected 'cert <subject common name> <role>'");
      p.name = f[1];
      if (!ParseRole(f[2], &p.role)) {
        return bad(absl::StrCat("role '", f[2], "': expected submitter, reader or admin"));
      }
      ids.certs_.push_back(p);
    } else {
      return bad(absl::StrCat("'", f[0], "': expected 'token' or 'cert'"));
    }
    if (!names.insert(p.name).second) {
      return bad(absl::StrCat("name '", p.name, "' appears twice"));
    }
  }
  if (ids.size() == 0) {
    return absl::InvalidArgumentError(
        absl::StrCat("--tokens-file ", file, ": no 'token' or 'cert' line"));
  }
  ids.required_ = true;
  return ids;
}

std::optional<Principal> Identities::ForToken(const std::string& token) const {
  const std::string d = RawSha256(token);
  std::optional<Principal> found;
  // Every entry compared, in constant time each: the time does not tell which one matched.
  for (const auto& e : tokens_) {
    if (CRYPTO_memcmp(e.sha256.data(), d.data(), d.size()) == 0) found = e.principal;
  }
  return found;
}

Principal Identities::ForCertificate(const std::string& cn) const {
  for (const auto& p : certs_) {
    if (p.name == cn) return p;
  }
  return Principal{cn, Role::kSubmitter};
}

grpc::Status CallGuard::Check(grpc::ServerContext* ctx, Principal* caller) const {
  if (!identities_.required()) {
    *caller = Principal{"anonymous", Role::kAdmin};
  } else {
    const auto& md = ctx->client_metadata();
    auto it = md.find("authorization");
    if (it != md.end()) {
      const std::string value(it->second.data(), it->second.size());
      constexpr absl::string_view kBearer = "Bearer ";
      auto p = absl::StartsWith(value, kBearer) ? identities_.ForToken(value.substr(kBearer.size()))
                                                : std::nullopt;
      if (!p) return grpc::Status(grpc::StatusCode::UNAUTHENTICATED, "wrong bearer token");
      *caller = *p;
    } else {
      // A client certificate reaches here only verified against --tls-client-ca.
      auto auth = ctx->auth_context();
      std::string cn;
      if (auth && auth->IsPeerAuthenticated()) {
        for (const auto& v : auth->FindPropertyValues(GRPC_X509_CN_PROPERTY_NAME)) {
          cn.assign(v.data(), v.size());
        }
      }
      if (cn.empty()) {
        return grpc::Status(grpc::StatusCode::UNAUTHENTICATED,
                            "missing bearer token (metadata 'authorization') or client "
                            "certificate");
      }
      *caller = identities_.ForCertificate(cn);
    }
  }
  if (draining()) {
    return grpc::Status(grpc::StatusCode::UNAVAILABLE,
                        "the server is shutting down; retry after it restarts");
  }
  return grpc::Status::OK;
}

grpc::Status CallGuard::MayRead(const Principal& caller, const std::string& creator,
                                const std::string& what) {
  if (caller.role == Role::kSubmitter && creator != caller.name) {
    return Denied(caller, absl::StrCat("may not read ", what, ", created by someone else"));
  }
  return grpc::Status::OK;
}

grpc::Status CallGuard::MayWrite(const Principal& caller, const std::string& creator,
                                 const std::string& what) {
  if (caller.role == Role::kReader) return Denied(caller, absl::StrCat("may not change ", what));
  if (caller.role == Role::kSubmitter && creator != caller.name) {
    return Denied(caller, absl::StrCat("may not change ", what, ", created by someone else"));
  }
  return grpc::Status::OK;
}

grpc::Status CallGuard::MayCreate(const Principal& caller, const std::string& what) {
  if (caller.role == Role::kReader) return Denied(caller, absl::StrCat("may not create ", what));
  return grpc::Status::OK;
}

std::string CallGuard::ListFilter(const Principal& caller) {
  return caller.role == Role::kSubmitter ? caller.name : std::string();
}

}  // namespace decima::server
