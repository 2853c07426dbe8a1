// decima-server: the gRPC service. Flags (each also an environment variable):
//   --listen ADDR         DECIMA_LISTEN          default 127.0.0.1:50051
//   --data-dir DIR        DECIMA_DATA_DIR        default $XDG_DATA_HOME/decima or ./decima-data
//   --store S             DECIMA_STORE           sqlite (default) or postgresql://...
//   --store-file F        DECIMA_STORE_FILE      the --store value read from a file (a Secret)
//   --workers N           DECIMA_WORKERS         default 1
//   --max-queued N        DECIMA_MAX_QUEUED      default 1000
//   --max-upload-mb N     DECIMA_MAX_UPLOAD_MB   default 2048
//   --token-file F        DECIMA_TOKEN_FILE      one bearer token, its holder is admin
//   --tokens-file F       DECIMA_TOKENS_FILE     principals and roles (call_guard.h)
//   --tls-cert F --tls-key F  DECIMA_TLS_CERT / DECIMA_TLS_KEY
//   --tls-client-ca F     DECIMA_TLS_CLIENT_CA   require client certificates signed by F
//   --audit-log F         DECIMA_AUDIT_LOG       default <data-dir>/audit-<hostname>.log
// `decima-server --run-job REQUEST` is the job child process (worker_process.h).
#include <fcntl.h>
#include <signal.h>
#include <sys/file.h>
#include <unistd.h>

#include <grpcpp/grpcpp.h>
#include <grpcpp/health_check_service_interface.h>
#include <grpcpp/security/server_credentials.h>
#include <grpcpp/security/tls_certificate_provider.h>
#include <grpcpp/security/tls_credentials_options.h>
#include <CLI/CLI.hpp>
#include <algorithm>
#include <atomic>
#include <cstdlib>
#include <fstream>
#include <sstream>
#include <thread>

#include "absl/strings/ascii.h"
#include "absl/strings/match.h"
#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "server/access/tls_files.h"
#include "server/api/grpc_util.h"
#include "server/api/service.h"
#include "server/dicom/dicom_receiver.h"
#include "server/dicom/dicom_sender.h"
#include "server/jobs/lease_reaper.h"
#include "server/jobs/worker_process.h"
#include "server/util/ids.h"
#include "server/util/periodic_task.h"
#include "spdlog/spdlog.h"

namespace fs = std::filesystem;
using namespace decima::server;

namespace {

std::string DefaultDataDir() {
  if (const char* x = std::getenv("XDG_DATA_HOME"); x != nullptr && *x != '\0') {
    return (fs::path(x) / "decima").string();
  }
  return "./decima-data";
}

absl::StatusOr<std::string> ReadFileText(const std::string& path, const char* what) {
  std::ifstream in(path, std::ios::binary);
  if (!in) return absl::NotFoundError(absl::StrCat(what, " ", path, ": cannot open"));
  std::stringstream ss;
  ss << in.rdbuf();
  return ss.str();
}

int RunJobMode(const char* request_file) { return RunJobProcess(request_file, kWorkerFd); }

// What main() below returns; kept next to it so the two stay in step.
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

}  // namespace

int main(int argc, char** argv) {
  if (argc == 3 && std::string(argv[1]) == "--run-job") return RunJobMode(argv[2]);
  EnableDcmtkTcpNoDelay();  // before any thread: setenv is not thread-safe

  CLI::App app{
      "decima-server: turns uploaded medical volumes into simplified tetrahedral "
      "meshes, as queued jobs (gRPC API decima.v1)"};
  app.set_version_flag("--version", std::string("decima-server ") + DECIMA_VERSION);
  app.footer(kExitCodes);
  std::string listen = "127.0.0.1:50051", data_dir = DefaultDataDir(), token_file, tokens_file,
              tls_cert, tls_key, tls_client_ca, audit_log, port_file;
  std::string store_spec = "sqlite", store_file;
  int tls_reload_seconds = 10, audit_max_mb = 64, audit_files = 10;
  int workers = 1, max_queued = 1000, max_attempts = 3, store_connections = 8,
      store_retry_seconds = 30;
  int64_t max_upload_mb = 2048, worker_memory_mb = 0;
  int64_t disk_reserve_mb = 64;
  double drain_seconds = 30, heartbeat_seconds = 5, lease_seconds = 15;
  double blob_grace_seconds = 3600, upload_expiry_seconds = 86400;
  bool allow_faults = false, no_fsync = false;
  app.add_option("--listen", listen, "address to serve on (host:port)")
      ->envname("DECIMA_LISTEN")
      ->capture_default_str();
  app.add_option("--data-dir", data_dir, "folder of the job store, blobs and artifacts")
      ->envname("DECIMA_DATA_DIR")
      ->capture_default_str();
  auto* store_opt =
      app.add_option("--store", store_spec,
                     "job store: 'sqlite' (embedded, in --data-dir) or a PostgreSQL URI "
                     "postgresql://user@host:port/db shared by replicas (which then share "
                     "--data-dir)")
          ->envname("DECIMA_STORE")
          ->capture_default_str();
  app.add_option("--store-file", store_file,
                 "file holding the --store value (e.g. a mounted Kubernetes Secret)")
      ->envname("DECIMA_STORE_FILE")
      ->check(CLI::ExistingFile)
      ->excludes(store_opt);
  app.add_option("--store-connections", store_connections,
                 "PostgreSQL connections in the pool (one more listens for events)")
      ->envname("DECIMA_STORE_CONNECTIONS")
      ->check(CLI::Range(1, 64))
      ->capture_default_str();
  app.add_option("--store-retry-seconds", store_retry_seconds,
                 "how long a call waits for a lost PostgreSQL to come back before it fails "
                 "UNAVAILABLE")
      ->envname("DECIMA_STORE_RETRY_SECONDS")
      ->check(CLI::Range(1, 3600))
      ->capture_default_str();
  app.add_option("--workers", workers, "jobs run at once (one child process each)")
      ->envname("DECIMA_WORKERS")
      ->check(CLI::Range(1, 256))
      ->capture_default_str();
  app.add_option("--max-queued", max_queued, "queued jobs before CreateJob is refused")
      ->envname("DECIMA_MAX_QUEUED")
      ->check(CLI::Range(1, 10000000))
      ->capture_default_str();
  app.add_option("--max-upload-mb", max_upload_mb,
                 "largest blob accepted (an upload, or an instance received by C-STORE), MiB")
      ->envname("DECIMA_MAX_UPLOAD_MB")
      ->check(CLI::Range(int64_t{1}, int64_t{1} << 30))
      ->capture_default_str();
  auto* single = app.add_option("--token-file", token_file,
                                "file holding the one bearer token every call needs (its "
                                "holder is the principal 'admin')")
                     ->envname("DECIMA_TOKEN_FILE")
                     ->check(CLI::ExistingFile);
  app.add_option("--tokens-file", tokens_file,
                 "principals: lines 'token <sha256 of token> <name> <submitter|reader|admin>' "
                 "and 'cert <client certificate CN> <role>'")
      ->envname("DECIMA_TOKENS_FILE")
      ->check(CLI::ExistingFile)
      ->excludes(single);
  auto* cert = app.add_option("--tls-cert", tls_cert, "PEM certificate chain: serve TLS")
                   ->envname("DECIMA_TLS_CERT")
                   ->check(CLI::ExistingFile);
  auto* key = app.add_option("--tls-key", tls_key, "PEM private key for --tls-cert")
                  ->envname("DECIMA_TLS_KEY")
                  ->check(CLI::ExistingFile);
  cert->needs(key);
  key->needs(cert);
  app.add_option("--tls-client-ca", tls_client_ca,
                 "PEM CA: require client certificates it signed (mutual TLS); the certificate's "
                 "CN is the principal unless a bearer token is sent")
      ->envname("DECIMA_TLS_CLIENT_CA")
      ->check(CLI::ExistingFile)
      ->needs(cert);
  app.add_option("--tls-reload-seconds", tls_reload_seconds,
                 "how often the TLS files are checked for changes (new ones serve new "
                 "connections; open streams keep theirs)")
      ->envname("DECIMA_TLS_RELOAD_SECONDS")
      ->check(CLI::Range(1, 86400))
      ->capture_default_str();
  app.add_option("--audit-log", audit_log,
                 "audit log file: one JSON line per state-changing call; one server per file "
                 "(default <data-dir>/audit-<hostname>.log, -2, -3, ... for a further server on "
                 "the host)")
      ->envname("DECIMA_AUDIT_LOG");
  app.add_option("--audit-max-mb", audit_max_mb, "audit log size before it is rotated, MiB")
      ->envname("DECIMA_AUDIT_MAX_MB")
      ->check(CLI::Range(1, 1 << 20))
      ->capture_default_str();
  app.add_option("--audit-files", audit_files, "rotated audit log files kept")
      ->envname("DECIMA_AUDIT_FILES")
      ->check(CLI::Range(1, 10000))
      ->capture_default_str();
  app.add_option("--max-attempts", max_attempts,
                 "claims of a job whose worker is lost before it fails")
      ->envname("DECIMA_MAX_ATTEMPTS")
      ->check(CLI::Range(1, 100))
      ->capture_default_str();
  app.add_option("--lease-seconds", lease_seconds, "job lease, renewed every third of it")
      ->envname("DECIMA_LEASE_SECONDS")
      ->check(CLI::Range(1.0, 3600.0))
      ->capture_default_str();
  app.add_option("--drain-seconds", drain_seconds,
                 "on SIGTERM, how long running jobs may finish (their watchers see the time "
                 "left) before they are requeued; a requeued job resumes after its last "
                 "finished stage")
      ->envname("DECIMA_DRAIN_SECONDS")
      ->check(CLI::Range(0.0, 86400.0))
      ->capture_default_str();
  app.add_option("--heartbeat-seconds", heartbeat_seconds, "WatchJob heartbeat period")
      ->envname("DECIMA_HEARTBEAT_SECONDS")
      ->check(CLI::Range(0.05, 3600.0))
      ->capture_default_str();
  app.add_option("--worker-memory-mb", worker_memory_mb,
                 "the most memory one job may use, MiB (0: 80% of physical memory); a job whose "
                 "volume needs more fails before it starts")
      ->envname("DECIMA_WORKER_MEMORY_MB")
      ->check(CLI::Range(int64_t{0}, int64_t{1} << 40))
      ->capture_default_str();
  app.add_option("--disk-reserve-mb", disk_reserve_mb,
                 "space kept in data-dir/reserve so deletes work on a full disk, MiB (0: none)")
      ->envname("DECIMA_DISK_RESERVE_MB")
      ->check(CLI::Range(int64_t{0}, int64_t{1} << 20))
      ->capture_default_str();
  app.add_option("--blob-grace-seconds", blob_grace_seconds,
                 "an uploaded blob no volume uses is kept this long for its CreateVolume")
      ->envname("DECIMA_BLOB_GRACE_SECONDS")
      ->check(CLI::Range(1.0, 1e8))
      ->capture_default_str();
  app.add_option("--upload-expiry-seconds", upload_expiry_seconds,
                 "an interrupted upload idle this long is deleted")
      ->envname("DECIMA_UPLOAD_EXPIRY_SECONDS")
      ->check(CLI::Range(1.0, 1e8))
      ->capture_default_str();
  app.add_flag("--allow-faults", allow_faults,
               "read the test fault seam (metadata decima-test-fault) on CreateJob (tests only)")
      ->envname("DECIMA_ALLOW_FAULTS");
  app.add_flag("--no-fsync", no_fsync, "do not fdatasync blobs before commit (benchmarks)")
      ->envname("DECIMA_NO_FSYNC");
  app.add_option("--port-file", port_file, "write the bound port here once serving (tests)")
      ->envname("DECIMA_PORT_FILE");
  std::string dicom_listen, dicom_aet = "DECIMA", dicom_routes;
  double dicom_quiet_seconds = DicomReceiverOptions().quiet_seconds;
  int64_t dicom_min_free_mb = 1024;
  app.add_option("--dicom-listen", dicom_listen,
                 "receive DICOM by C-STORE on HOST:PORT (off when unset)")
      ->envname("DECIMA_DICOM_LISTEN");
  app.add_option("--dicom-aet", dicom_aet, "our DICOM AE title (the called AE title accepted)")
      ->envname("DECIMA_DICOM_AET")
      ->capture_default_str();
  app.add_option("--dicom-quiet-seconds", dicom_quiet_seconds,
                 "a received series is checked once no instance came for this long")
      ->envname("DECIMA_DICOM_QUIET_SECONDS")
      ->check(CLI::Range(0.1, 3600.0))
      ->capture_default_str();
  app.add_option("--dicom-routes", dicom_routes,
                 "JSON file: job spec and result destination per calling/called AE title")
      ->envname("DECIMA_DICOM_ROUTES")
      ->check(CLI::ExistingFile);
  app.add_option("--dicom-min-free-mb", dicom_min_free_mb,
                 "refuse DICOM associations when the data dir has less free disk, MiB")
      ->envname("DECIMA_DICOM_MIN_FREE_MB")
      ->check(CLI::Range(int64_t{0}, int64_t{1} << 40))
      ->capture_default_str();
  int dicom_max_associations = DicomReceiverOptions().max_associations;
  int dicom_max_per_peer = DicomReceiverOptions().max_per_peer;
  int dicom_timeout_seconds = DicomReceiverOptions().timeout_seconds;
  app.add_option("--dicom-max-associations", dicom_max_associations,
                 "DICOM associations served at once; more connections are closed")
      ->envname("DECIMA_DICOM_MAX_ASSOCIATIONS")
      ->check(CLI::Range(1, 1000))
      ->capture_default_str();
  app.add_option("--dicom-max-per-peer", dicom_max_per_peer,
                 "DICOM associations served at once from one peer address")
      ->envname("DECIMA_DICOM_MAX_PER_PEER")
      ->check(CLI::Range(1, 1000))
      ->capture_default_str();
  app.add_option("--dicom-timeout-seconds", dicom_timeout_seconds,
                 "a DICOM connection is closed when its association request takes longer, or "
                 "its association stays silent this long (C-STOREs over --max-upload-mb abort "
                 "their association)")
      ->envname("DECIMA_DICOM_TIMEOUT_SECONDS")
      ->check(CLI::Range(1, 3600))
      ->capture_default_str();
  double dicom_incomplete_expiry = DicomReceiverOptions().incomplete_expiry_seconds;
  int64_t dicom_quota_mb = DicomReceiverOptions().quota_mb;
  app.add_option("--dicom-incomplete-expiry", dicom_incomplete_expiry,
                 "seconds a received series may wait incomplete before its instances and blobs "
                 "are removed (0 never)")
      ->envname("DECIMA_DICOM_INCOMPLETE_EXPIRY")
      ->check(CLI::Range(0.0, 1e9))
      ->capture_default_str();
  app.add_option("--dicom-quota-mb", dicom_quota_mb,
                 "MiB of waiting (not yet queued) instances per calling AE title; more are "
                 "refused (0 no limit)")
      ->envname("DECIMA_DICOM_QUOTA_MB")
      ->check(CLI::Range(int64_t{0}, int64_t{1} << 40))
      ->capture_default_str();
  try {
    app.parse(argc, argv);
  } catch (const CLI::ParseError& e) {
    // CLI11's own codes (100-127, one per kind of mistake) would be one more table to learn;
    // every usage error is 2, as in the CLI.
    return app.exit(e) == 0 ? 0 : 2;
  }

  DicomReceiverOptions dicom;
  if (!dicom_listen.empty()) {
    const size_t colon = dicom_listen.rfind(':');
    int dport = 0;
    if (colon == std::string::npos || colon == 0 ||
        !absl::SimpleAtoi(dicom_listen.substr(colon + 1), &dport) || dport < 1 || dport > 65535) {
      spdlog::error("--dicom-listen {}: expected HOST:PORT with a port 1..65535", dicom_listen);
      return 1;
    }
    if (dicom_aet.empty() || dicom_aet.size() > 16) {
      spdlog::error("--dicom-aet '{}': expected 1..16 characters", dicom_aet);
      return 1;
    }
    dicom.host = dicom_listen.substr(0, colon);
    dicom.port = dport;
    dicom.aet = dicom_aet;
    dicom.quiet_seconds = dicom_quiet_seconds;
    dicom.min_free_mb = dicom_min_free_mb;
    dicom.incomplete_expiry_seconds = dicom_incomplete_expiry;
    dicom.quota_mb = dicom_quota_mb;
    dicom.max_queued = max_queued;
    dicom.max_associations = dicom_max_associations;
    dicom.max_per_peer = dicom_max_per_peer;
    dicom.timeout_seconds = dicom_timeout_seconds;
    dicom.max_instance_bytes = max_upload_mb << 20;
    if (!dicom_routes.empty()) {
      auto routes = LoadDicomRoutes(dicom_routes);
      if (!routes.ok()) {
        spdlog::error("{}", std::string(routes.status().message()));
        return 1;
      }
      dicom.routes = std::move(*routes);
    }
  }

  spdlog::set_pattern("%Y-%m-%dT%H:%M:%S.%e %^%l%$ %v");

  // Block the shutdown signals in every thread; one thread waits for them below. The job
  // children unblock them before exec.
  sigset_t sigs;
  sigemptyset(&sigs);
  sigaddset(&sigs, SIGTERM);
  sigaddset(&sigs, SIGINT);
  pthread_sigmask(SIG_BLOCK, &sigs, nullptr);
  signal(SIGPIPE, SIG_IGN);

  std::error_code ec;
  fs::create_directories(data_dir, ec);
  if (ec) {
    spdlog::error("--data-dir {}: {}", data_dir, ec.message());
    return 1;
  }
  fs::path data = fs::absolute(data_dir);
  if (!store_file.empty()) {
    auto s = ReadFileText(store_file, "--store-file");
    if (!s.ok()) {
      spdlog::error("{}", std::string(s.status().message()));
      return 1;
    }
    store_spec = std::string(absl::StripAsciiWhitespace(*s));
  }
  const bool postgres =
      absl::StartsWith(store_spec, "postgresql://") || absl::StartsWith(store_spec, "postgres://");
  if (!postgres && store_spec != "sqlite") {
    spdlog::error(
        "--store: expected 'sqlite' or a PostgreSQL URI 'postgresql://user@host:port/db', got "
        "'{}'",
        store_spec.substr(0, store_spec.find(':')));  // never log a password
    return 1;
  }
  // SQLite: one server per data dir (exclusive lock); the kernel drops it when the process
  // dies, so after a crash every RUNNING job's owner is known to be gone. PostgreSQL: replicas
  // share the data dir (shared lock), which keeps an embedded server out of it.
  int lock_fd = ::open((data / "LOCK").c_str(), O_RDWR | O_CREAT | O_CLOEXEC, 0644);
  if (lock_fd < 0 || ::flock(lock_fd, (postgres ? LOCK_SH : LOCK_EX) | LOCK_NB) != 0) {
    spdlog::error("--data-dir {}: used by {} (LOCK is held)", data.string(),
                  postgres ? "a decima-server with the embedded store" : "another decima-server");
    return 1;
  }
  const std::string owner = absl::StrCat("pid", ::getpid(), "-", NewId());

  Identities identities;
  if (!token_file.empty()) {
    auto t = ReadFileText(token_file, "--token-file");
    if (!t.ok()) {
      spdlog::error("{}", std::string(t.status().message()));
      return 1;
    }
    std::string token(absl::StripAsciiWhitespace(*t));
    if (token.empty()) {
      spdlog::error("--token-file {}: empty", token_file);
      return 1;
    }
    identities = Identities::SingleToken(token);
  }
  if (!tokens_file.empty()) {
    auto t = ReadFileText(tokens_file, "--tokens-file");
    auto ids = t.ok() ? Identities::Parse(*t, tokens_file) : t.status();
    if (!ids.ok()) {
      spdlog::error("{}", std::string(ids.status().message()));
      return 1;
    }
    identities = std::move(*ids);
  }
  if (!tls_client_ca.empty()) identities.RequireClientCertificates();
  // gRPC watches checked copies of the TLS files, never the files themselves (tls_files.h).
  std::unique_ptr<TlsFileGuard> tls_guard;
  if (!tls_cert.empty()) {
    auto g = TlsFileGuard::Start(tls_cert, tls_key, tls_client_ca,
                                 std::chrono::seconds(tls_reload_seconds));
    if (!g.ok()) {
      spdlog::error("{}", std::string(g.status().message()));
      return 1;
    }
    tls_guard = std::move(*g);
  }
  // One writer per audit file: by default a file per host (replicas sharing the data dir), and
  // a further server on the same host takes the next free number.
  absl::StatusOr<std::shared_ptr<AuditLog>> audit;
  for (int n = 1; n <= 16; ++n) {
    audit =
        AuditLog::Open(audit_log.empty() ? DefaultAuditPath(data.string(), n) : audit_log,
                       static_cast<size_t>(audit_max_mb) << 20, static_cast<size_t>(audit_files));
    if (!audit_log.empty() || !absl::IsFailedPrecondition(audit.status())) break;
  }
  if (!audit.ok()) {
    spdlog::error("{}", std::string(audit.status().message()));
    return 1;
  }

  absl::StatusOr<std::unique_ptr<JobStore>> store;
  if (postgres) {
    PostgresStoreOptions po;
    po.connections = store_connections;
    po.reconnect_timeout = std::chrono::seconds(store_retry_seconds);
    po.application_name = absl::StrCat("decima-server ", owner);
    store = OpenPostgresJobStore(store_spec, po);
  } else {
    store = OpenSqliteJobStore(DataDir(data).job_store().string());
  }
  if (!store.ok()) {
    spdlog::error("{}", store.status().ToString());
    return 1;
  }
  auto blobs = LocalBlobStore::Open(data / "blobs", !no_fsync);
  if (!blobs.ok()) {
    spdlog::error("{}", blobs.status().ToString());
    return 1;
  }
  EventBus bus;
  // A job queued anywhere (another replica's CreateJob, Retry or reaper) wakes an idle worker
  // here at once instead of at its next 1 s poll. The pool is made below; the listener may
  // already run on the store's event thread.
  std::atomic<WorkerPool*> wake_pool{nullptr};
  (*store)->SetListener([&bus, &wake_pool](const std::string& id, const decima::v1::JobEvent& ev) {
    bus.Publish(id, ev);
    if (ev.has_state_change() && ev.state_change().state() == decima::v1::QUEUED) {
      if (WorkerPool* p = wake_pool.load()) p->Notify();
    }
  });
  (*store)->SetWatchedJobs([&bus] { return bus.ActiveJobs(); });

  // Only an exclusive store (ours, under LOCK) knows its RUNNING jobs are orphans; a shared store
  // leaves them to the lease reaper, since other replicas may be running them.
  if ((*store)->exclusive()) {
    auto recovered = (*store)->RecoverLeases(/*all=*/true, max_attempts);
    if (!recovered.ok()) {
      spdlog::error("recovering jobs: {}", recovered.status().ToString());
      return 1;
    }
    for (const auto& id : recovered->requeued) {
      spdlog::info("job {} QUEUED again (its worker was lost when the server stopped)", id);
    }
    for (const auto& id : recovered->failed) {
      spdlog::info("job {} FAILED/CANCELLED on recovery", id);
    }
  }

  WorkerPoolOptions wo;
  wo.workers = workers;
  wo.owner = owner;
  wo.runner.data_dir = DataDir(data);
  wo.runner.worker_exe = fs::read_symlink("/proc/self/exe", ec);
  wo.runner.lease_ms = static_cast<int64_t>(lease_seconds * 1000);
  wo.runner.worker_memory_mb = worker_memory_mb;
  wo.runner.allow_faults = allow_faults;
  WorkerPool pool(store->get(), wo);
  wake_pool = &pool;

  ServiceOptions so;
  so.data_dir = DataDir(data);
  const bool auth = identities.required();
  so.identities = std::move(identities);
  so.audit = *audit;
  so.max_upload_bytes = max_upload_mb << 20;
  so.max_queued = max_queued;
  so.allow_faults = allow_faults;
  so.heartbeat_ms = static_cast<int64_t>(heartbeat_seconds * 1000);
  so.blob_sweep.grace = std::chrono::seconds(static_cast<int64_t>(blob_grace_seconds));
  so.blob_sweep.partial_expiry = std::chrono::seconds(static_cast<int64_t>(upload_expiry_seconds));
  so.disk_reserve_bytes = disk_reserve_mb << 20;
  Services services(so, store->get(), blobs->get(), &bus, &pool);
  auto collect = [&services] {
    const BlobSweepStats st = services.CollectGarbage();
    if (st.blobs_removed + st.partials_removed > 0) {
      spdlog::info("collector: removed {} unreferenced blob(s) and {} abandoned upload(s), {}",
                   st.blobs_removed, st.partials_removed, HumanBytes(st.bytes_freed));
    }
  };
  collect();  // what a crash or an earlier run left
  // A quarter of the shortest lifetime, between 1 s and 5 min.
  const double period_s =
      std::clamp(std::min(blob_grace_seconds, upload_expiry_seconds) / 4, 1.0, 300.0);
  PeriodicTask collector(std::chrono::milliseconds(static_cast<int64_t>(period_s * 1000)), collect);

  grpc::EnableDefaultHealthCheckService(true);
  grpc::ServerBuilder builder;
  std::shared_ptr<grpc::ServerCredentials> creds = grpc::InsecureServerCredentials();
  if (!tls_cert.empty()) {
    // The files are re-read every --tls-reload-seconds and swapped in when they changed (a
    // renewed certificate, a new client CA): new handshakes use them, established connections
    // and their streams are not touched. gRPC reads the guard's checked copies, so a broken or
    // empty file renamed into place keeps the last good set serving.
    auto provider = std::make_shared<grpc::experimental::FileWatcherCertificateProvider>(
        tls_guard->served_key(), tls_guard->served_cert(), tls_guard->served_client_ca(),
        static_cast<unsigned>(tls_reload_seconds));
    grpc::experimental::TlsServerCredentialsOptions tls(provider);
    tls.watch_identity_key_cert_pairs();
    if (!tls_client_ca.empty()) {
      tls.watch_root_certs();
      tls.set_cert_request_type(GRPC_SSL_REQUEST_AND_REQUIRE_CLIENT_CERTIFICATE_AND_VERIFY);
    } else {
      tls.set_cert_request_type(GRPC_SSL_DONT_REQUEST_CLIENT_CERTIFICATE);
    }
    creds = grpc::experimental::TlsServerCredentials(tls);
  }
  int port = 0;
  // gRPC sets SO_REUSEPORT by default, so a second server would share the port (and clients
  // would alternate between two job stores): a busy address must be an error at start.
  builder.AddChannelArgument(GRPC_ARG_ALLOW_REUSEPORT, 0);
  builder.AddListeningPort(listen, creds, &port);
  builder.RegisterService(services.uploads());
  builder.RegisterService(services.volumes());
  builder.RegisterService(services.jobs());
  builder.RegisterService(services.artifacts());
  builder.RegisterService(services.reflection());
  builder.SetMaxReceiveMessageSize(4 << 20);
  std::unique_ptr<grpc::Server> server = builder.BuildAndStart();
  if (!server || port == 0) {
    spdlog::error(
        "--listen {}: cannot bind (in use by another process, or not an address of "
        "this machine)",
        listen);
    return 1;
  }
  server->GetHealthCheckService()->SetServingStatus(true);
  // Health follows the store (issue 35 part 7: with PostgreSQL down the server said SERVING
  // while every call failed): one quick round trip a second, NOT_SERVING while it fails.
  std::atomic<bool> store_ok{true}, draining{false};
  PeriodicTask store_health(std::chrono::seconds(1), [&] {
    const absl::Status st = (*store)->Ping();
    if (st.ok() == store_ok.load()) return;
    store_ok = st.ok();
    if (st.ok()) {
      spdlog::info("job store reachable again: health SERVING");
    } else {
      spdlog::error("job store unreachable, health NOT_SERVING: {}", st.ToString());
    }
    if (!draining) server->GetHealthCheckService()->SetServingStatus(st.ok());
  });
  pool.Start();
  std::unique_ptr<DicomReceiver> receiver;
  if (!dicom_listen.empty()) {
    dicom.audit = *audit;
    receiver = std::make_unique<DicomReceiver>(dicom, &so.data_dir, store->get(), blobs->get(),
                                               services.catalog(), &pool);
    if (auto st = receiver->Start(); !st.ok()) {
      spdlog::error("{}", st.ToString());
      return 1;
    }
  }
  spdlog::info(
      "decima-server {} listening on {} (port {}), data {}, store {}, audit {}, {} worker(s){}{}",
      owner, listen, port, data.string(), postgres ? "postgresql" : "sqlite", (*audit)->path(),
      workers, auth ? ", callers identified" : ", no authentication",
      tls_cert.empty() ? "" : (tls_client_ca.empty() ? ", TLS" : ", mutual TLS"));
  if (!port_file.empty()) {
    std::string tmp = port_file + ".tmp";
    std::ofstream(tmp) << port << "\n";
    fs::rename(tmp, port_file, ec);
  }

  // Lease expiry on its own timer: lapsed leases (a worker lost in another replica, a stuck
  // store) go back to the queue eight times per lease period, so a lost job runs again within
  // lease + lease/8 of its holder's last renewal (one indexed query per sweep).
  LeaseReaper reaper(store->get(), std::chrono::milliseconds(wo.runner.lease_ms / 8), max_attempts,
                     [&pool] { pool.Notify(); });
  reaper.Start();

  int sig = 0;
  sigwait(&sigs, &sig);
  spdlog::info(
      "signal {}: draining (health NOT_SERVING, new calls UNAVAILABLE, running jobs "
      "get {} s)",
      sig, drain_seconds);
  draining = true;
  store_health.Stop();
  services.StartDraining();
  if (receiver) receiver->Stop();  // no new series while draining
  server->GetHealthCheckService()->SetServingStatus(false);
  wake_pool = nullptr;
  // The bus stays open through the drain: watchers of running jobs see the drain's progress and
  // the requeue; it closes (ending every watch) once no job runs here.
  pool.Drain(std::chrono::milliseconds(static_cast<int64_t>(drain_seconds * 1000)));
  bus.Close();
  reaper.Stop();
  collector.Stop();
  server->Shutdown(std::chrono::system_clock::now() + std::chrono::seconds(2));
  // Deletes since the collector's last pass give their pages back now, so a stopped server
  // leaves a compact job store (the soak measures the data dir after deleting everything).
  if (absl::Status st = (*store)->Compact(); !st.ok()) {
    spdlog::warn("compacting the job store: {}", st.ToString());
  }
  // The store's event thread publishes to the bus: stop it while the bus exists.
  store->reset();
  spdlog::info("decima-server stopped");
  return 0;
}
