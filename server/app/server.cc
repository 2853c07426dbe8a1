#include "server/app/server.h"

#include <fcntl.h>
#include <sys/file.h>
#include <unistd.h>

#include <grpcpp/health_check_service_interface.h>
#include <grpcpp/security/server_credentials.h>
#include <grpcpp/security/tls_certificate_provider.h>
#include <grpcpp/security/tls_credentials_options.h>
#include <algorithm>
#include <fstream>
#include <sstream>

#include "absl/strings/ascii.h"
#include "absl/strings/match.h"
#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "core/common/status.h"
#include "server/api/grpc_util.h"
#include "server/jobs/job_memory.h"
#include "server/util/ids.h"
#include "spdlog/spdlog.h"

namespace decima::server {
namespace {

namespace fs = std::filesystem;

absl::StatusOr<std::string> ReadFileText(const std::string& path, const char* what) {
  std::ifstream in(path, std::ios::binary);
  if (!in) return absl::NotFoundError(absl::StrCat(what, " ", path, ": cannot open"));
  std::stringstream ss;
  ss << in.rdbuf();
  return ss.str();
}

// A failure whose log line is the status in full ("INTERNAL: ..."), as the store's errors are.
absl::Status Logged(const absl::Status& st) { return absl::Status(st.code(), st.ToString()); }

}  // namespace

absl::StatusOr<std::unique_ptr<Server>> Server::Start(const ServerOptions& options) {
  std::unique_ptr<Server> s(new Server(options));
  DECIMA_RETURN_IF_ERROR(s->ConfigureDicom());
  spdlog::set_pattern("%Y-%m-%dT%H:%M:%S.%e %^%l%$ %v");
  s->BlockStopSignals();
  DECIMA_RETURN_IF_ERROR(s->LockDataDir());
  DECIMA_RETURN_IF_ERROR(s->LoadIdentities());
  DECIMA_RETURN_IF_ERROR(s->StartTls());
  DECIMA_RETURN_IF_ERROR(s->OpenAudit());
  DECIMA_RETURN_IF_ERROR(s->OpenStores());
  DECIMA_RETURN_IF_ERROR(s->RecoverJobs());
  s->StartServices();
  DECIMA_RETURN_IF_ERROR(s->StartGrpc());
  s->WatchStoreHealth();
  s->pool_->Start();
  DECIMA_RETURN_IF_ERROR(s->StartDicom());
  s->AnnounceListening();
  // Lease expiry on its own timer: lapsed leases (a worker lost in another replica, a stuck
  // store) go back to the queue eight times per lease period, so a lost job runs again within
  // lease + lease/8 of its holder's last renewal (one indexed query per sweep).
  Server* self = s.get();
  s->reaper_ = std::make_unique<LeaseReaper>(
      s->store_.get(), std::chrono::milliseconds(s->pool_options_.runner.lease_ms / 8),
      options.max_attempts, [self] { self->pool_->Notify(); });
  s->reaper_->Start();
  return s;
}

// The receiver's options from the --dicom-* flags, checked before anything starts.
absl::Status Server::ConfigureDicom() {
  const ServerOptions& o = options_;
  if (o.dicom_listen.empty()) return absl::OkStatus();
  const size_t colon = o.dicom_listen.rfind(':');
  int dport = 0;
  if (colon == std::string::npos || colon == 0 ||
      !absl::SimpleAtoi(o.dicom_listen.substr(colon + 1), &dport) || dport < 1 || dport > 65535) {
    return absl::InvalidArgumentError(absl::StrCat("--dicom-listen ", o.dicom_listen,
                                                   ": expected HOST:PORT with a port 1..65535"));
  }
  if (o.dicom_aet.empty() || o.dicom_aet.size() > 16) {
    return absl::InvalidArgumentError(
        absl::StrCat("--dicom-aet '", o.dicom_aet, "': expected 1..16 characters"));
  }
  dicom_.host = o.dicom_listen.substr(0, colon);
  dicom_.port = dport;
  dicom_.aet = o.dicom_aet;
  dicom_.quiet_seconds = o.dicom_quiet_seconds;
  dicom_.min_free_mb = o.dicom_min_free_mb;
  dicom_.incomplete_expiry_seconds = o.dicom_incomplete_expiry;
  dicom_.quota_mb = o.dicom_quota_mb;
  dicom_.max_queued = o.max_queued;
  dicom_.max_associations = o.dicom_max_associations;
  dicom_.max_per_peer = o.dicom_max_per_peer;
  dicom_.timeout_seconds = o.dicom_timeout_seconds;
  dicom_.max_instance_bytes = o.max_upload_mb << 20;
  if (!o.dicom_routes.empty()) {
    auto routes = LoadDicomRoutes(o.dicom_routes);
    if (!routes.ok()) return absl::InvalidArgumentError(routes.status().message());
    dicom_.routes = std::move(*routes);
  }
  return absl::OkStatus();
}

// Block the shutdown signals in every thread; one thread waits for them (WaitForStopSignal).
// The job children unblock them before exec.
void Server::BlockStopSignals() {
  sigemptyset(&stop_signals_);
  sigaddset(&stop_signals_, SIGTERM);
  sigaddset(&stop_signals_, SIGINT);
  pthread_sigmask(SIG_BLOCK, &stop_signals_, nullptr);
  signal(SIGPIPE, SIG_IGN);
}

absl::Status Server::LockDataDir() {
  std::error_code ec;
  fs::create_directories(options_.data_dir, ec);
  if (ec) {
    return absl::InternalError(absl::StrCat("--data-dir ", options_.data_dir, ": ", ec.message()));
  }
  data_ = fs::absolute(options_.data_dir);
  store_uri_ = options_.store;
  if (!options_.store_file.empty()) {
    auto s = ReadFileText(options_.store_file, "--store-file");
    if (!s.ok()) return s.status();
    store_uri_ = std::string(absl::StripAsciiWhitespace(*s));
  }
  postgres_ =
      absl::StartsWith(store_uri_, "postgresql://") || absl::StartsWith(store_uri_, "postgres://");
  if (!postgres_ && store_uri_ != "sqlite") {
    return absl::InvalidArgumentError(absl::StrCat(
        "--store: expected 'sqlite' or a PostgreSQL URI 'postgresql://user@host:port/db', got '",
        store_uri_.substr(0, store_uri_.find(':')), "'"));  // never log a password
  }
  // SQLite: one server per data dir (exclusive lock); the kernel drops it when the process
  // dies, so after a crash every RUNNING job's owner is known to be gone. PostgreSQL: replicas
  // share the data dir (shared lock), which keeps an embedded server out of it.
  lock_fd_ = ::open((data_ / "LOCK").c_str(), O_RDWR | O_CREAT | O_CLOEXEC, 0644);
  if (lock_fd_ < 0 || ::flock(lock_fd_, (postgres_ ? LOCK_SH : LOCK_EX) | LOCK_NB) != 0) {
    return absl::FailedPreconditionError(absl::StrCat(
        "--data-dir ", data_.string(), ": used by ",
        postgres_ ? "a decima-server with the embedded store" : "another decima-server",
        " (LOCK is held)"));
  }
  owner_ = absl::StrCat("pid", ::getpid(), "-", NewId());
  return absl::OkStatus();
}

absl::Status Server::LoadIdentities() {
  if (!options_.token_file.empty()) {
    DECIMA_ASSIGN_OR_RETURN(const std::string t, ReadFileText(options_.token_file, "--token-file"));
    std::string token(absl::StripAsciiWhitespace(t));
    if (token.empty()) {
      return absl::InvalidArgumentError(
          absl::StrCat("--token-file ", options_.token_file, ": empty"));
    }
    identities_ = Identities::SingleToken(token);
  }
  if (!options_.tokens_file.empty()) {
    auto t = ReadFileText(options_.tokens_file, "--tokens-file");
    auto ids = t.ok() ? Identities::Parse(*t, options_.tokens_file) : t.status();
    if (!ids.ok()) return ids.status();
    identities_ = std::move(*ids);
  }
  if (!options_.tls_client_ca.empty()) identities_.RequireClientCertificates();
  callers_identified_ = identities_.required();
  return absl::OkStatus();
}

// gRPC watches checked copies of the TLS files, never the files themselves (tls_files.h).
absl::Status Server::StartTls() {
  if (options_.tls_cert.empty()) return absl::OkStatus();
  DECIMA_ASSIGN_OR_RETURN(
      tls_guard_, TlsFileGuard::Start(options_.tls_cert, options_.tls_key, options_.tls_client_ca,
                                      std::chrono::seconds(options_.tls_reload_seconds)));
  return absl::OkStatus();
}

// One writer per audit file: by default a file per host (replicas sharing the data dir), and
// a further server on the same host takes the next free number.
absl::Status Server::OpenAudit() {
  absl::StatusOr<std::shared_ptr<AuditLog>> audit;
  for (int n = 1; n <= 16; ++n) {
    audit = AuditLog::Open(
        options_.audit_log.empty() ? DefaultAuditPath(data_.string(), n) : options_.audit_log,
        static_cast<size_t>(options_.audit_max_mb) << 20,
        static_cast<size_t>(options_.audit_files));
    if (!options_.audit_log.empty() || !absl::IsFailedPrecondition(audit.status())) break;
  }
  if (!audit.ok()) return audit.status();
  audit_ = std::move(*audit);
  return absl::OkStatus();
}

// The job store, the blob store, and the store's events on the bus.
absl::Status Server::OpenStores() {
  absl::StatusOr<std::unique_ptr<JobStore>> store;
  if (postgres_) {
    PostgresStoreOptions po;
    po.connections = options_.store_connections;
    po.reconnect_timeout = std::chrono::seconds(options_.store_retry_seconds);
    po.application_name = absl::StrCat("decima-server ", owner_);
    store = OpenPostgresJobStore(store_uri_, po);
  } else {
    store = OpenSqliteJobStore(DataDir(data_).job_store().string());
  }
  if (!store.ok()) return Logged(store.status());
  store_ = std::move(*store);
  auto blobs = LocalBlobStore::Open(data_ / "blobs", !options_.no_fsync);
  if (!blobs.ok()) return Logged(blobs.status());
  blobs_ = std::move(*blobs);
  // A job queued anywhere (another replica's CreateJob, Retry or reaper) wakes an idle worker
  // here at once instead of at its next 1 s poll. The pool is made later; the listener may
  // already run on the store's event thread.
  store_->SetListener([this](const std::string& id, const v1::JobEvent& ev) {
    bus_.Publish(id, ev);
    if (ev.has_state_change() && ev.state_change().state() == v1::QUEUED) {
      if (WorkerPool* p = wake_pool_.load()) p->Notify();
    }
  });
  store_->SetWatchedJobs([this] { return bus_.ActiveJobs(); });
  return absl::OkStatus();
}

// Only an exclusive store (ours, under LOCK) knows its RUNNING jobs are orphans; a shared store
// leaves them to the lease reaper, since other replicas may be running them.
absl::Status Server::RecoverJobs() {
  if (!store_->exclusive()) return absl::OkStatus();
  auto recovered = store_->RecoverLeases(/*all=*/true, options_.max_attempts);
  if (!recovered.ok()) {
    return absl::Status(recovered.status().code(),
                        absl::StrCat("recovering jobs: ", recovered.status().ToString()));
  }
  for (const auto& id : recovered->requeued) {
    spdlog::info("job {} QUEUED again (its worker was lost when the server stopped)", id);
  }
  for (const auto& id : recovered->failed) {
    spdlog::info("job {} FAILED/CANCELLED on recovery", id);
  }
  return absl::OkStatus();
}

// The worker pool (not started yet), the services and the blob collector.
void Server::StartServices() {
  const ServerOptions& o = options_;
  std::error_code ec;
  pool_options_.workers = o.workers;
  pool_options_.owner = owner_;
  pool_options_.runner.data_dir = DataDir(data_);
  pool_options_.runner.worker_exe = fs::read_symlink("/proc/self/exe", ec);
  pool_options_.runner.lease_ms = static_cast<int64_t>(o.lease_seconds * 1000);
  pool_options_.runner.worker_memory_mb = o.worker_memory_mb;
  pool_options_.runner.allow_faults = o.allow_faults;
  pool_ = std::make_unique<WorkerPool>(store_.get(), pool_options_);
  wake_pool_ = pool_.get();

  ServiceOptions& so = service_options_;
  so.data_dir = DataDir(data_);
  so.identities = std::move(identities_);
  so.audit = audit_;
  so.max_upload_bytes = o.max_upload_mb << 20;
  so.max_queued = o.max_queued;
  so.job_memory_cap_bytes = JobMemoryCapBytes(o.worker_memory_mb);
  so.allow_faults = o.allow_faults;
  so.heartbeat_ms = static_cast<int64_t>(o.heartbeat_seconds * 1000);
  so.blob_sweep.grace = std::chrono::seconds(static_cast<int64_t>(o.blob_grace_seconds));
  so.blob_sweep.partial_expiry =
      std::chrono::seconds(static_cast<int64_t>(o.upload_expiry_seconds));
  so.disk_reserve_bytes = o.disk_reserve_mb << 20;
  services_ = std::make_unique<Services>(so, store_.get(), blobs_.get(), &bus_, pool_.get());
  auto collect = [services = services_.get()] {
    const BlobSweepStats st = services->CollectGarbage();
    if (st.blobs_removed + st.partials_removed > 0) {
      spdlog::info("collector: removed {} unreferenced blob(s) and {} abandoned upload(s), {}",
                   st.blobs_removed, st.partials_removed, HumanBytes(st.bytes_freed));
    }
  };
  collect();  // what a crash or an earlier run left
  // A quarter of the shortest lifetime, between 1 s and 5 min.
  const double period_s =
      std::clamp(std::min(o.blob_grace_seconds, o.upload_expiry_seconds) / 4, 1.0, 300.0);
  collector_ = std::make_unique<PeriodicTask>(
      std::chrono::milliseconds(static_cast<int64_t>(period_s * 1000)), collect);
}

absl::Status Server::StartGrpc() {
  grpc::EnableDefaultHealthCheckService(true);
  grpc::ServerBuilder builder;
  std::shared_ptr<grpc::ServerCredentials> creds = grpc::InsecureServerCredentials();
  if (tls_guard_) {
    // The files are re-read every --tls-reload-seconds and swapped in when they changed (a
    // renewed certificate, a new client CA): new handshakes use them, established connections
    // and their streams are not touched. gRPC reads the guard's checked copies, so a broken or
    // empty file renamed into place keeps the last good set serving.
    auto provider = std::make_shared<grpc::experimental::FileWatcherCertificateProvider>(
        tls_guard_->served_key(), tls_guard_->served_cert(), tls_guard_->served_client_ca(),
        static_cast<unsigned>(options_.tls_reload_seconds));
    grpc::experimental::TlsServerCredentialsOptions tls(provider);
    tls.watch_identity_key_cert_pairs();
    if (!options_.tls_client_ca.empty()) {
      tls.watch_root_certs();
      tls.set_cert_request_type(GRPC_SSL_REQUEST_AND_REQUIRE_CLIENT_CERTIFICATE_AND_VERIFY);
    } else {
      tls.set_cert_request_type(GRPC_SSL_DONT_REQUEST_CLIENT_CERTIFICATE);
    }
    creds = grpc::experimental::TlsServerCredentials(tls);
  }
  // gRPC sets SO_REUSEPORT by default, so a second server would share the port (and clients
  // would alternate between two job stores): a busy address must be an error at start.
  builder.AddChannelArgument(GRPC_ARG_ALLOW_REUSEPORT, 0);
  builder.AddListeningPort(options_.listen, creds, &port_);
  builder.RegisterService(services_->uploads());
  builder.RegisterService(services_->volumes());
  builder.RegisterService(services_->jobs());
  builder.RegisterService(services_->artifacts());
  builder.RegisterService(services_->reflection());
  builder.SetMaxReceiveMessageSize(4 << 20);
  grpc_ = builder.BuildAndStart();
  if (!grpc_ || port_ == 0) {
    return absl::UnavailableError(
        absl::StrCat("--listen ", options_.listen,
                     ": cannot bind (in use by another process, or not an address of this "
                     "machine)"));
  }
  grpc_->GetHealthCheckService()->SetServingStatus(true);
  return absl::OkStatus();
}

// Health follows the store (issue 35 part 7: with PostgreSQL down the server said SERVING while
// every call failed): one quick round trip a second, NOT_SERVING while it fails.
void Server::WatchStoreHealth() {
  store_health_ = std::make_unique<PeriodicTask>(std::chrono::seconds(1), [this] {
    const absl::Status st = store_->Ping();
    if (st.ok() == store_ok_.load()) return;
    store_ok_ = st.ok();
    if (st.ok()) {
      spdlog::info("job store reachable again: health SERVING");
    } else {
      spdlog::error("job store unreachable, health NOT_SERVING: {}", st.ToString());
    }
    if (!draining_) grpc_->GetHealthCheckService()->SetServingStatus(st.ok());
  });
}

absl::Status Server::StartDicom() {
  if (options_.dicom_listen.empty()) return absl::OkStatus();
  dicom_.audit = audit_;
  receiver_ = std::make_unique<DicomReceiver>(dicom_, &service_options_.data_dir, store_.get(),
                                              blobs_.get(), services_->catalog(), pool_.get());
  if (absl::Status st = receiver_->Start(); !st.ok()) return Logged(st);
  return absl::OkStatus();
}

void Server::AnnounceListening() {
  const ServerOptions& o = options_;
  spdlog::info(
      "decima-server {} listening on {} (port {}), data {}, store {}, audit {}, {} worker(s){}{}",
      owner_, o.listen, port_, data_.string(), postgres_ ? "postgresql" : "sqlite", audit_->path(),
      o.workers, callers_identified_ ? ", callers identified" : ", no authentication",
      o.tls_cert.empty() ? "" : (o.tls_client_ca.empty() ? ", TLS" : ", mutual TLS"));
  if (!o.port_file.empty()) {
    std::string tmp = o.port_file + ".tmp";
    std::ofstream(tmp) << port_ << "\n";
    std::error_code ec;
    fs::rename(tmp, o.port_file, ec);
  }
}

int Server::WaitForStopSignal() {
  int sig = 0;
  sigwait(&stop_signals_, &sig);
  return sig;
}

void Server::Drain(int signal) {
  spdlog::info(
      "signal {}: draining (health NOT_SERVING, new calls UNAVAILABLE, running jobs "
      "get {} s)",
      signal, options_.drain_seconds);
  draining_ = true;
  store_health_->Stop();
  services_->StartDraining();
  if (receiver_) receiver_->Stop();  // no new series while draining
  grpc_->GetHealthCheckService()->SetServingStatus(false);
  wake_pool_ = nullptr;
  // The bus stays open through the drain: watchers of running jobs see the drain's progress and
  // the requeue; it closes (ending every watch) once no job runs here.
  pool_->Drain(std::chrono::milliseconds(static_cast<int64_t>(options_.drain_seconds * 1000)));
  bus_.Close();
  reaper_->Stop();
  collector_->Stop();
  grpc_->Shutdown(std::chrono::system_clock::now() + std::chrono::seconds(2));
  // Deletes since the collector's last pass give their pages back now, so a stopped server
  // leaves a compact job store (the soak measures the data dir after deleting everything).
  if (absl::Status st = store_->Compact(); !st.ok()) {
    spdlog::warn("compacting the job store: {}", st.ToString());
  }
  // The store's event thread publishes to the bus: stop it while the bus exists.
  store_.reset();
  spdlog::info("decima-server stopped");
}

}  // namespace decima::server
