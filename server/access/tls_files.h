// The TLS files: checked at start-up, so that a wrong, mismatched or expired certificate stops
// the server with a message naming the file instead of a server whose handshakes all fail; and
// checked again at every reload before gRPC sees them (TlsFileGuard), so that a broken file
// renamed into place cannot reach gRPC's certificate provider. Given an empty key or certificate
// that provider aborted the process on an assertion, and given a broken non-empty pair it
// served it and every new handshake failed (issue 35 part 4).
#pragma once

#include <memory>
#include <string>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "server/util/periodic_task.h"

namespace decima::server {

// `cert` is a PEM chain whose first certificate is valid now and matches the PEM private key
// `key`; `client_ca` (may be empty) holds at least one PEM certificate valid now.
// INVALID_ARGUMENT naming the flag, the file and the problem.
absl::Status CheckTlsFiles(const std::string& cert, const std::string& key,
                           const std::string& client_ca);

// The same check on the files' contents (`cert_file` etc. name them in the message);
// `client_ca_pem` is not checked when `client_ca_file` is empty.
absl::Status CheckTlsPem(const std::string& cert_pem, const std::string& key_pem,
                         const std::string& client_ca_pem, const std::string& cert_file,
                         const std::string& key_file, const std::string& client_ca_file);

// Stands between the operator's TLS files and gRPC's FileWatcherCertificateProvider: gRPC
// watches copies in a private folder (mkdtemp under $TMPDIR, mode 0700, removed on
// destruction), and every `period` the guard re-reads the operator's files and, when they
// changed, copies them there only if they pass CheckTlsPem. A changed set that fails is logged
// once (error, naming the file and the problem) and the last good set keeps serving; a later
// good set is taken as usual. The copies are replaced by rename, key first, so gRPC's reader
// (which re-reads when a file's time changed while it read) never pairs a new certificate
// with an old key for long.
// Thread-safety: the copying runs on the guard's own thread; the accessors are constant.
class TlsFileGuard {
 public:
  // Checks the files (CheckTlsFiles) and makes the first copies.
  static absl::StatusOr<std::unique_ptr<TlsFileGuard>> Start(const std::string& cert,
                                                             const std::string& key,
                                                             const std::string& client_ca,
                                                             std::chrono::milliseconds period);
  ~TlsFileGuard();

  // The copies gRPC is to watch ("" for the CA when there is none).
  std::string served_cert() const { return dir_ + "/cert.pem"; }
  std::string served_key() const { return dir_ + "/key.pem"; }
  std::string served_client_ca() const { return client_ca_.empty() ? "" : dir_ + "/ca.pem"; }

 private:
  TlsFileGuard() = default;
  void Reload();

  std::string cert_, key_, client_ca_, dir_;
  // Contents last served and last refused (a refused set is logged once).
  std::string served_, refused_;
  std::unique_ptr<PeriodicTask> task_;
};

}  // namespace decima::server
