// Start-up check of the TLS files, so that a wrong, mismatched or expired certificate stops the
// server with a message naming the file instead of a server whose handshakes all fail (gRPC's
// file-watching certificate provider loads them asynchronously and only logs).
#pragma once

#include <string>

#include "absl/status/status.h"

namespace decima::server {

// `cert` is a PEM chain whose first certificate is valid now and matches the PEM private key
// `key`; `client_ca` (may be empty) holds at least one PEM certificate valid now.
// INVALID_ARGUMENT naming the flag, the file and the problem.
absl::Status CheckTlsFiles(const std::string& cert, const std::string& key,
                           const std::string& client_ca);

}  // namespace decima::server
