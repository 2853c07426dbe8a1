// decima-server's flags: ServerOptions from the command line and the environment.
#include <CLI/CLI.hpp>
#include <cstdlib>
#include <filesystem>

#include "server/app/server_options.h"
#include "server/dicom/dicom_receiver.h"

namespace decima::server {
namespace {

std::string DefaultDataDir() {
  if (const char* x = std::getenv("XDG_DATA_HOME"); x != nullptr && *x != '\0') {
    return (std::filesystem::path(x) / "decima").string();
  }
  return "./decima-data";
}

// What main() returns; kept next to the flags so the two stay in step.
const char* kExitCodes = R"(
Exit codes:
  0  stopped by SIGTERM or SIGINT after draining (also --help, --version)
  1  could not start: a flag's value or a file it names is invalid (--store, --dicom-listen,
     --tokens-file, TLS files, --dicom-routes, ...), --data-dir is locked by another
     decima-server, the job store cannot be opened, --listen or --dicom-listen cannot be bound;
     the log line names the flag or file
  2  usage: unknown flag, missing value, value out of range, a named file does not exist
The job child process (`decima-server --run-job`, started by the server) has its own codes
(worker_process.h).)";

// --help lists the flags in the order they are added: serving and storage, access, jobs, DICOM.
void AddServingFlags(CLI::App& app, ServerOptions& o) {
  app.add_option("--listen", o.listen, "address to serve on (host:port)")
      ->envname("DECIMA_LISTEN")
      ->capture_default_str();
  app.add_option("--data-dir", o.data_dir, "folder of the job store, blobs and artifacts")
      ->envname("DECIMA_DATA_DIR")
      ->capture_default_str();
  auto* store_opt =
      app.add_option("--store", o.store,
                     "job store: 'sqlite' (embedded, in --data-dir) or a PostgreSQL URI "
                     "postgresql://user@host:port/db shared by replicas (which then share "
                     "--data-dir)")
          ->envname("DECIMA_STORE")
          ->capture_default_str();
  app.add_option("--store-file", o.store_file,
                 "file holding the --store value (e.g. a mounted Kubernetes Secret)")
      ->envname("DECIMA_STORE_FILE")
      ->check(CLI::ExistingFile)
      ->excludes(store_opt);
  app.add_option("--store-connections", o.store_connections,
                 "PostgreSQL connections in the pool (one more listens for events)")
      ->envname("DECIMA_STORE_CONNECTIONS")
      ->check(CLI::Range(1, 64))
      ->capture_default_str();
  app.add_option("--store-retry-seconds", o.store_retry_seconds,
                 "how long a call waits for a lost PostgreSQL to come back before it fails "
                 "UNAVAILABLE")
      ->envname("DECIMA_STORE_RETRY_SECONDS")
      ->check(CLI::Range(1, 3600))
      ->capture_default_str();
  app.add_option("--workers", o.workers, "jobs run at once (one child process each)")
      ->envname("DECIMA_WORKERS")
      ->check(CLI::Range(1, 256))
      ->capture_default_str();
  app.add_option("--max-queued", o.max_queued, "queued jobs before CreateJob is refused")
      ->envname("DECIMA_MAX_QUEUED")
      ->check(CLI::Range(1, 10000000))
      ->capture_default_str();
  app.add_option("--max-upload-mb", o.max_upload_mb,
                 "largest blob accepted (an upload, or an instance received by C-STORE), MiB")
      ->envname("DECIMA_MAX_UPLOAD_MB")
      ->check(CLI::Range(int64_t{1}, int64_t{1} << 30))
      ->capture_default_str();
}

void AddAccessFlags(CLI::App& app, ServerOptions& o) {
  auto* single = app.add_option("--token-file", o.token_file,
                                "file holding the one bearer token every call needs (its "
                                "holder is the principal 'admin')")
                     ->envname("DECIMA_TOKEN_FILE")
                     ->check(CLI::ExistingFile);
  app.add_option("--tokens-file", o.tokens_file,
                 "principals: lines 'token <sha256 of token> <name> <submitter|reader|admin>' "
                 "and 'cert <client certificate CN> <role>'")
      ->envname("DECIMA_TOKENS_FILE")
      ->check(CLI::ExistingFile)
      ->excludes(single);
  auto* cert = app.add_option("--tls-cert", o.tls_cert, "PEM certificate chain: serve TLS")
                   ->envname("DECIMA_TLS_CERT")
                   ->check(CLI::ExistingFile);
  auto* key = app.add_option("--tls-key", o.tls_key, "PEM private key for --tls-cert")
                  ->envname("DECIMA_TLS_KEY")
                  ->check(CLI::ExistingFile);
  cert->needs(key);
  key->needs(cert);
  app.add_option("--tls-client-ca", o.tls_client_ca,
                 "PEM CA: require client certificates it signed (mutual TLS); the certificate's "
                 "CN is the principal unless a bearer token is sent")
      ->envname("DECIMA_TLS_CLIENT_CA")
      ->check(CLI::ExistingFile)
      ->needs(cert);
  app.add_option("--tls-reload-seconds", o.tls_reload_seconds,
                 "how often the TLS files are checked for changes (new ones serve new "
                 "connections; open streams keep theirs)")
      ->envname("DECIMA_TLS_RELOAD_SECONDS")
      ->check(CLI::Range(1, 86400))
      ->capture_default_str();
  app.add_option("--audit-log", o.audit_log,
                 "audit log file: one JSON line per state-changing call; one server per file "
                 "(default <data-dir>/audit-<hostname>.log, -2, -3, ... for a further server on "
                 "the host)")
      ->envname("DECIMA_AUDIT_LOG");
  app.add_option("--audit-max-mb", o.audit_max_mb, "audit log size before it is rotated, MiB")
      ->envname("DECIMA_AUDIT_MAX_MB")
      ->check(CLI::Range(1, 1 << 20))
      ->capture_default_str();
  app.add_option("--audit-files", o.audit_files, "rotated audit log files kept")
      ->envname("DECIMA_AUDIT_FILES")
      ->check(CLI::Range(1, 10000))
      ->capture_default_str();
}

void AddJobFlags(CLI::App& app, ServerOptions& o) {
  app.add_option("--max-attempts", o.max_attempts,
                 "claims of a job whose worker is lost before it fails")
      ->envname("DECIMA_MAX_ATTEMPTS")
      ->check(CLI::Range(1, 100))
      ->capture_default_str();
  app.add_option("--lease-seconds", o.lease_seconds, "job lease, renewed every third of it")
      ->envname("DECIMA_LEASE_SECONDS")
      ->check(CLI::Range(1.0, 3600.0))
      ->capture_default_str();
  app.add_option("--drain-seconds", o.drain_seconds,
                 "on SIGTERM, how long running jobs may finish (their watchers see the time "
                 "left) before they are requeued; a requeued job resumes after its last "
                 "finished stage")
      ->envname("DECIMA_DRAIN_SECONDS")
      ->check(CLI::Range(0.0, 86400.0))
      ->capture_default_str();
  app.add_option("--heartbeat-seconds", o.heartbeat_seconds, "WatchJob heartbeat period")
      ->envname("DECIMA_HEARTBEAT_SECONDS")
      ->check(CLI::Range(0.05, 3600.0))
      ->capture_default_str();
  app.add_option("--worker-memory-mb", o.worker_memory_mb,
                 "the most memory one job may use, MiB (0: 80% of physical memory); a job whose "
                 "volume needs more fails before it starts")
      ->envname("DECIMA_WORKER_MEMORY_MB")
      ->check(CLI::Range(int64_t{0}, int64_t{1} << 40))
      ->capture_default_str();
  app.add_option("--disk-reserve-mb", o.disk_reserve_mb,
                 "space kept in data-dir/reserve so deletes work on a full disk, MiB (0: none)")
      ->envname("DECIMA_DISK_RESERVE_MB")
      ->check(CLI::Range(int64_t{0}, int64_t{1} << 20))
      ->capture_default_str();
  app.add_option("--blob-grace-seconds", o.blob_grace_seconds,
                 "an uploaded blob no volume uses is kept this long for its CreateVolume")
      ->envname("DECIMA_BLOB_GRACE_SECONDS")
      ->check(CLI::Range(1.0, 1e8))
      ->capture_default_str();
  app.add_option("--upload-expiry-seconds", o.upload_expiry_seconds,
                 "an interrupted upload idle this long is deleted")
      ->envname("DECIMA_UPLOAD_EXPIRY_SECONDS")
      ->check(CLI::Range(1.0, 1e8))
      ->capture_default_str();
  app.add_flag("--allow-faults", o.allow_faults,
               "read the test fault seam (metadata decima-test-fault) on CreateJob (tests only)")
      ->envname("DECIMA_ALLOW_FAULTS");
  app.add_flag("--no-fsync", o.no_fsync, "do not fdatasync blobs before commit (benchmarks)")
      ->envname("DECIMA_NO_FSYNC");
  app.add_option("--port-file", o.port_file, "write the bound port here once serving (tests)")
      ->envname("DECIMA_PORT_FILE");
}

void AddDicomFlags(CLI::App& app, ServerOptions& o) {
  app.add_option("--dicom-listen", o.dicom_listen,
                 "receive DICOM by C-STORE on HOST:PORT (off when unset)")
      ->envname("DECIMA_DICOM_LISTEN");
  app.add_option("--dicom-aet", o.dicom_aet, "our DICOM AE title (the called AE title accepted)")
      ->envname("DECIMA_DICOM_AET")
      ->capture_default_str();
  app.add_option("--dicom-quiet-seconds", o.dicom_quiet_seconds,
                 "a received series is checked once no instance came for this long")
      ->envname("DECIMA_DICOM_QUIET_SECONDS")
      ->check(CLI::Range(0.1, 3600.0))
      ->capture_default_str();
  app.add_option("--dicom-routes", o.dicom_routes,
                 "JSON file: job spec and result destination per calling/called AE title")
      ->envname("DECIMA_DICOM_ROUTES")
      ->check(CLI::ExistingFile);
  app.add_option("--dicom-min-free-mb", o.dicom_min_free_mb,
                 "refuse DICOM associations when the data dir has less free disk, MiB")
      ->envname("DECIMA_DICOM_MIN_FREE_MB")
      ->check(CLI::Range(int64_t{0}, int64_t{1} << 40))
      ->capture_default_str();
  app.add_option("--dicom-max-associations", o.dicom_max_associations,
                 "DICOM associations served at once; more connections are closed")
      ->envname("DECIMA_DICOM_MAX_ASSOCIATIONS")
      ->check(CLI::Range(1, 1000))
      ->capture_default_str();
  app.add_option("--dicom-max-per-peer", o.dicom_max_per_peer,
                 "DICOM associations served at once from one peer address")
      ->envname("DECIMA_DICOM_MAX_PER_PEER")
      ->check(CLI::Range(1, 1000))
      ->capture_default_str();
  app.add_option("--dicom-timeout-seconds", o.dicom_timeout_seconds,
                 "a DICOM connection is closed when its association request takes longer, or "
                 "its association stays silent this long (C-STOREs over --max-upload-mb abort "
                 "their association)")
      ->envname("DECIMA_DICOM_TIMEOUT_SECONDS")
      ->check(CLI::Range(1, 3600))
      ->capture_default_str();
  app.add_option("--dicom-incomplete-expiry", o.dicom_incomplete_expiry,
                 "seconds a received series may wait incomplete before its instances and blobs "
                 "are removed (0 never)")
      ->envname("DECIMA_DICOM_INCOMPLETE_EXPIRY")
      ->check(CLI::Range(0.0, 1e9))
      ->capture_default_str();
  app.add_option("--dicom-quota-mb", o.dicom_quota_mb,
                 "MiB of waiting (not yet queued) instances per calling AE title; more are "
                 "refused (0 no limit)")
      ->envname("DECIMA_DICOM_QUOTA_MB")
      ->check(CLI::Range(int64_t{0}, int64_t{1} << 40))
      ->capture_default_str();
}

}  // namespace

ServerOptions::ServerOptions() : data_dir(DefaultDataDir()) {
  const DicomReceiverOptions dicom;
  dicom_quiet_seconds = dicom.quiet_seconds;
  dicom_max_associations = dicom.max_associations;
  dicom_max_per_peer = dicom.max_per_peer;
  dicom_timeout_seconds = dicom.timeout_seconds;
  dicom_incomplete_expiry = dicom.incomplete_expiry_seconds;
  dicom_quota_mb = dicom.quota_mb;
}

std::optional<int> ParseFlags(int argc, char** argv, ServerOptions* options) {
  CLI::App app{
      "decima-server: turns uploaded medical volumes into simplified tetrahedral "
      "meshes, as queued jobs (gRPC API decima.v1)"};
  app.set_version_flag("--version", std::string("decima-server ") + DECIMA_VERSION);
  app.footer(kExitCodes);
  AddServingFlags(app, *options);
  AddAccessFlags(app, *options);
  AddJobFlags(app, *options);
  AddDicomFlags(app, *options);
  try {
    app.parse(argc, argv);
  } catch (const CLI::ParseError& e) {
    // CLI11's own codes (100-127, one per kind of mistake) would be one more table to learn;
    // every usage error is 2, as in the CLI.
    return app.exit(e) == 0 ? 0 : 2;
  }
  return std::nullopt;
}

}  // namespace decima::server
