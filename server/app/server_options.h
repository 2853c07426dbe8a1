// decima-server's flags as values (each also an environment variable; `decima-server --help`
// lists them), and ParseFlags, which fills them from the command line.
#pragma once

#include <cstdint>
#include <optional>
#include <string>

namespace decima::server {

// One member per flag, named after it; the initializers are the flags' defaults.
struct ServerOptions {
  // Serving and storage.
  std::string listen = "127.0.0.1:50051";
  std::string data_dir;          // default $XDG_DATA_HOME/decima or ./decima-data
  std::string store = "sqlite";  // "sqlite" or a PostgreSQL URI
  std::string store_file;        // the --store value read from this file (a Secret)
  int store_connections = 8;
  int store_retry_seconds = 30;
  int workers = 1;
  int max_queued = 1000;
  int64_t max_upload_mb = 2048;
  // Access: callers, TLS, audit.
  std::string token_file, tokens_file;
  std::string tls_cert, tls_key, tls_client_ca;
  int tls_reload_seconds = 10;
  std::string audit_log;  // default <data-dir>/audit-<hostname>.log
  int audit_max_mb = 64;
  int audit_files = 10;
  // Jobs and their lifetime.
  int max_attempts = 3;
  double lease_seconds = 15;
  double drain_seconds = 30;
  double heartbeat_seconds = 5;
  int64_t worker_memory_mb = 0;
  int64_t disk_reserve_mb = 64;
  double blob_grace_seconds = 3600;
  double upload_expiry_seconds = 86400;
  bool allow_faults = false;
  bool no_fsync = false;
  std::string port_file;
  // The DICOM receiver (off while dicom_listen is empty); defaults from DicomReceiverOptions.
  std::string dicom_listen;
  std::string dicom_aet = "DECIMA";
  double dicom_quiet_seconds;
  std::string dicom_routes;
  int64_t dicom_min_free_mb = 1024;
  int dicom_max_associations;
  int dicom_max_per_peer;
  int dicom_timeout_seconds;
  double dicom_incomplete_expiry;
  int64_t dicom_quota_mb;

  ServerOptions();
};

// Fills `options` from argv (and the DECIMA_* environment). Returns the exit code when the
// process should stop now, after CLI11 printed what was asked or wrong: 0 after --help or
// --version, 2 for a usage error (unknown flag, missing value, value out of range, a named file
// that does not exist); nothing when the server should start.
std::optional<int> ParseFlags(int argc, char** argv, ServerOptions* options);

}  // namespace decima::server
