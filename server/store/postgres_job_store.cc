// The shared JobStore: PostgreSQL through libpqxx, for several decima-server replicas. The only
// file that includes libpqxx. Same design as the SQLite store: a few indexed columns (state,
// lease, request id) beside the serialized decima.v1.Job, which is the truth for everything
// else (fields added to Job travel without a migration); events are rows keyed by (job, seq).
//
// Across replicas:
//  - ClaimNext takes the oldest QUEUED row with FOR UPDATE SKIP LOCKED, so concurrent claimers
//    never wait on, nor share, a row; the claim increments lease_epoch (the fencing token).
//  - Lease expiry uses the database clock (clock_timestamp()), so replica clocks may differ.
//  - Every transaction that writes events ends with pg_notify('decima_events', 'job_id:seq')
//    (delivered on commit, payload far below the 8000-byte limit). One thread per store LISTENs
//    on its own connection, reads the event rows above what it delivered and hands them to the
//    listener in order; the rows stay the truth. After a lost connection it reconnects,
//    LISTENs again and re-reads every job it follows or that is watched here.
//  - The schema is a list of numbered migrations applied under an advisory lock.
//  - A lost connection is retried (new connection, same transaction body) until
//    `reconnect_timeout`; a commit whose outcome is unknown is UNAVAILABLE.
#include <pqxx/pqxx>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <condition_variable>
#include <deque>
#include <map>
#include <mutex>
#include <set>
#include <thread>
#include <tuple>
#include <utility>

#include "absl/strings/match.h"
#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"
#include "server/store/job_lifecycle.h"
#include "server/store/job_store.h"
#include "spdlog/spdlog.h"

namespace decima::server {
namespace {

constexpr char kChannel[] = "decima_events";
// pg_advisory_xact_lock key of schema migrations ("decima" in ASCII).
constexpr int64_t kMigrationLockKey = 0x646563696d61;

// The schema, one entry per version; never edit an applied entry, append a new one.
const char* const kMigrations[] = {
    // 1: jobs, events, volumes.
    R"sql(
      CREATE TABLE jobs(
        ord BIGSERIAL PRIMARY KEY,
        id TEXT UNIQUE NOT NULL,
        request_id TEXT UNIQUE,
        state INTEGER NOT NULL,
        lease_owner TEXT,
        lease_expiry TIMESTAMPTZ,
        lease_epoch BIGINT NOT NULL DEFAULT 0,
        cancel_requested BOOLEAN NOT NULL DEFAULT FALSE,
        volume TEXT NOT NULL,
        job BYTEA NOT NULL);
      CREATE INDEX jobs_by_state ON jobs(state, ord);
      CREATE INDEX jobs_running_by_expiry ON jobs(lease_expiry) WHERE state = 2;
      CREATE TABLE events(
        job_id TEXT NOT NULL, seq BIGINT NOT NULL, event BYTEA NOT NULL,
        PRIMARY KEY(job_id, seq));
      CREATE TABLE volumes(
        ord BIGSERIAL PRIMARY KEY,
        id TEXT UNIQUE NOT NULL,
        request_id TEXT UNIQUE,
        volume BYTEA NOT NULL);
      CREATE TABLE volume_blobs(
        volume_id TEXT NOT NULL, sha256 TEXT NOT NULL,
        PRIMARY KEY(volume_id, sha256));
      CREATE INDEX volume_blobs_by_sha ON volume_blobs(sha256);
    )sql",
    // 2: the creator of jobs and volumes (Job.creator / Volume.creator), for per-principal lists.
    R"sql(
      ALTER TABLE jobs ADD COLUMN creator TEXT NOT NULL DEFAULT '';
      ALTER TABLE volumes ADD COLUMN creator TEXT NOT NULL DEFAULT '';
      CREATE INDEX jobs_by_creator ON jobs(creator, ord);
      CREATE INDEX volumes_by_creator ON volumes(creator, ord);
    )sql",
    // 3: the DICOM receiver's state (server/dicom_receiver.h), as in the SQLite store: instances
    // received but not yet in a job, and one row per checked instance set.
    R"sql(
      CREATE TABLE dicom_instances(
        ord BIGSERIAL PRIMARY KEY,
        sop_instance_uid TEXT UNIQUE NOT NULL,
        series_instance_uid TEXT NOT NULL,
        sha256 TEXT NOT NULL,
        calling_ae TEXT NOT NULL, called_ae TEXT NOT NULL,
        received_ms BIGINT NOT NULL,
        aborted_ms BIGINT NOT NULL DEFAULT 0);
      CREATE INDEX dicom_instances_by_sha ON dicom_instances(sha256);
      CREATE INDEX dicom_instances_by_series ON dicom_instances(series_instance_uid);
      CREATE TABLE dicom_series(
        ord BIGSERIAL PRIMARY KEY,
        instance_set TEXT UNIQUE NOT NULL,
        series_instance_uid TEXT NOT NULL,
        job TEXT NOT NULL, reason TEXT NOT NULL, route TEXT NOT NULL,
        results_pending BOOLEAN NOT NULL, send_status TEXT NOT NULL,
        update_ms BIGINT NOT NULL,
        state INTEGER NOT NULL,
        calling_ae TEXT NOT NULL, called_ae TEXT NOT NULL,
        instance_count INTEGER NOT NULL,
        first_received_ms BIGINT NOT NULL, last_received_ms BIGINT NOT NULL);
      CREATE INDEX dicom_series_pending ON dicom_series(ord) WHERE results_pending;
    )sql",
    // 4: the receiver's state keyed by sender (dicom_receiver.h): an instance is unique per
    // (calling AE title, SOP Instance UID), not across senders, and knows its size (the
    // per-sender quota; 0 for rows from before, not counted); every receive of a series keeps
    // its own row (receive_key; a row from before is keyed by its instance set, one per set).
    R"sql(
      ALTER TABLE dicom_instances DROP CONSTRAINT dicom_instances_sop_instance_uid_key;
      ALTER TABLE dicom_instances ADD CONSTRAINT dicom_instances_by_sender_sop
        UNIQUE(calling_ae, sop_instance_uid);
      ALTER TABLE dicom_instances ADD COLUMN size_bytes BIGINT NOT NULL DEFAULT 0;
      DROP INDEX dicom_instances_by_series;
      CREATE INDEX dicom_instances_by_sender ON dicom_instances(calling_ae, series_instance_uid);
      ALTER TABLE dicom_series ADD COLUMN receive_key TEXT;
      UPDATE dicom_series SET receive_key = instance_set;
      ALTER TABLE dicom_series ALTER COLUMN receive_key SET NOT NULL;
      ALTER TABLE dicom_series ADD CONSTRAINT dicom_series_receive_key UNIQUE(receive_key);
      ALTER TABLE dicom_series DROP CONSTRAINT dicom_series_instance_set_key;
    )sql",
    // 5: volumes found by content (VolumeContentKey, volume_catalog.h): one row per creator and
    // content, also when replicas create it at once. NULL for rows from before (never reused).
    R"sql(
      ALTER TABLE volumes ADD COLUMN content_key TEXT;
      CREATE UNIQUE INDEX volumes_by_content ON volumes(creator, content_key);
    )sql",
    // 6: the DICOM association that brought each waiting instance and each receive
    // (dicom_receiver.h); "" for rows from before.
    R"sql(
      ALTER TABLE dicom_instances ADD COLUMN association_id TEXT NOT NULL DEFAULT '';
      ALTER TABLE dicom_series ADD COLUMN association_id TEXT NOT NULL DEFAULT '';
    )sql",
};
static_assert(v1::RUNNING == 2, "migration 1's partial index names RUNNING as 2");

pqxx::binarystring Bytes(const google::protobuf::MessageLite& m) {
  return pqxx::binarystring(m.SerializeAsString());
}

std::string FieldBytes(const pqxx::field& f) { return pqxx::binarystring(f).str(); }

absl::StatusOr<v1::Job> ParseJob(const pqxx::field& f) {
  v1::Job job;
  if (!job.ParseFromString(FieldBytes(f))) return absl::DataLossError("job store: bad job row");
  return job;
}

absl::StatusOr<v1::Volume> ParseVolume(const pqxx::field& f) {
  v1::Volume v;
  if (!v.ParseFromString(FieldBytes(f))) return absl::DataLossError("job store: bad volume row");
  return v;
}

// "{a,b}" for ids made of [0-9a-z-] (ParseName guarantees it) and numbers.
std::string TextArray(const std::vector<std::string>& items) {
  return absl::StrCat("{", absl::StrJoin(items, ","), "}");
}

constexpr char kInstanceColumns[] =
    "SELECT series_instance_uid, sop_instance_uid, sha256, calling_ae, called_ae, received_ms, "
    "aborted_ms, size_bytes, association_id FROM dicom_instances ";

// Rows of kInstanceColumns' columns, in order.
std::vector<DicomInstanceRecord> Instances(const pqxx::result& rows) {
  std::vector<DicomInstanceRecord> out;
  for (const auto& row : rows) {
    out.push_back({row[0].as<std::string>(), row[1].as<std::string>(), row[2].as<std::string>(),
                   row[3].as<std::string>(), row[4].as<std::string>(), row[5].as<int64_t>(),
                   row[6].as<int64_t>(), row[7].as<int64_t>(), row[8].as<std::string>()});
  }
  return out;
}

// A few connections shared by the store's callers; connections are made on demand and a broken
// one is dropped (the next caller makes a new one).
class ConnectionPool {
 public:
  ConnectionPool(std::string dsn, std::string app, int max)
      : dsn_(std::move(dsn)), app_(app), max_(max) {}

  // Blocks while all `max` connections are in use. Throws pqxx::broken_connection when the
  // server cannot be reached.
  std::unique_ptr<pqxx::connection> Acquire() {
    {
      std::unique_lock<std::mutex> lock(mu_);
      cv_.wait(lock, [&] { return !idle_.empty() || open_ < max_; });
      if (!idle_.empty()) {
        auto c = std::move(idle_.back());
        idle_.pop_back();
        return c;
      }
      ++open_;
    }
    try {
      return Connect(dsn_, app_);
    } catch (...) {
      std::lock_guard<std::mutex> lock(mu_);
      --open_;
      cv_.notify_one();
      throw;
    }
  }

  void Release(std::unique_ptr<pqxx::connection> c, bool broken) {
    std::lock_guard<std::mutex> lock(mu_);
    if (broken || !c->is_open()) {
      --open_;
      c.reset();
    } else {
      idle_.push_back(std::move(c));
    }
    cv_.notify_one();
  }

  static std::unique_ptr<pqxx::connection> Connect(const std::string& dsn, const std::string& app) {
    // libpqxx 6.4 races with itself when connections are set up on several threads at once
    // (ThreadSanitizer: shared state written in its connection start-up); setting up is rare.
    static std::mutex setup_mu;
    std::lock_guard<std::mutex> setup_lock(setup_mu);
    auto c = std::make_unique<pqxx::connection>(dsn);
    // A connection libpqxx silently re-opened would have lost its LISTEN and its session state:
    // we replace broken connections ourselves.
#pragma GCC diagnostic push
#pragma GCC diagnostic ignored "-Wdeprecated-declarations"
    c->inhibit_reactivation(true);
#pragma GCC diagnostic pop
    pqxx::nontransaction n(*c);
    n.exec("SET application_name = " + n.quote(app));
    return c;
  }

 private:
  const std::string dsn_, app_;
  const int max_;
  std::mutex mu_;
  std::condition_variable cv_;
  std::vector<std::unique_ptr<pqxx::connection>> idle_;
  int open_ = 0;
};

// Events written by one transaction: NOTIFY once per job with its newest sequence.
struct TxEvents {
  PendingEvents events;  // appended by the lifecycle rules (job_lifecycle.h)

  // Inserts the rows and queues the notifications (sent by PostgreSQL at commit).
  void Save(pqxx::work& w) {
    std::map<std::string, int64_t> newest;
    for (const auto& [id, ev] : events) {
      w.exec_params("INSERT INTO events(job_id, seq, event) VALUES($1,$2,$3)", id, ev.sequence(),
                    Bytes(ev));
      newest[id] = std::max(newest[id], ev.sequence());
    }
    for (const auto& [id, seq] : newest) {
      w.exec_params("SELECT pg_notify($1, $2)", kChannel, absl::StrCat(id, ":", seq));
    }
    events.clear();
  }
};

class PostgresJobStore : public JobStore {
 public:
  PostgresJobStore(std::string dsn, PostgresStoreOptions options)
      : dsn_(std::move(dsn)),
        options_(std::move(options)),
        pool_(dsn_, options_.application_name, std::max(1, options_.connections)) {}

  ~PostgresJobStore() override {
    stop_ = true;
    if (listen_thread_.joinable()) listen_thread_.join();
  }

  absl::Status Migrate() {
    return Run<absl::Status>("applying schema migrations", [&](pqxx::work& w) -> absl::Status {
      // Replicas starting together queue here; the first applies, the others find it done.
      w.exec_params("SELECT pg_advisory_xact_lock($1)", kMigrationLockKey);
      w.exec(
          "CREATE TABLE IF NOT EXISTS decima_schema_migrations("
          "version INTEGER PRIMARY KEY, applied_at TIMESTAMPTZ NOT NULL DEFAULT now())");
      const int known = static_cast<int>(std::size(kMigrations));
      const int have =
          w.exec("SELECT COALESCE(MAX(version), 0) FROM decima_schema_migrations")[0][0].as<int>();
      if (have > known) {
        return absl::FailedPreconditionError(absl::StrCat("the database's schema is version ", have,
                                                          ", newer than this server's (", known,
                                                          "); run a newer decima-server"));
      }
      for (int v = have + 1; v <= known; ++v) {
        w.exec(kMigrations[v - 1]);
        w.exec_params("INSERT INTO decima_schema_migrations(version) VALUES($1)", v);
        spdlog::info("job store: applied schema migration {}", v);
      }
      return absl::OkStatus();
    });
  }

  // Starts the event feed and waits until its LISTEN is in effect (events committed before
  // that are in the store, read by watchers through ListEvents).
  absl::Status StartListening() {
    listen_thread_ = std::thread([this] { ListenLoop(); });
    std::unique_lock<std::mutex> lock(listening_mu_);
    if (!listening_cv_.wait_for(lock, options_.reconnect_timeout, [&] { return listening_; })) {
      return absl::UnavailableError("job store: the event feed could not LISTEN");
    }
    return absl::OkStatus();
  }

  bool exclusive() const override { return false; }

  void SetListener(EventListener listener) override {
    std::lock_guard<std::mutex> lock(listener_mu_);
    listener_ = std::move(listener);
  }
  void SetWatchedJobs(std::function<std::vector<std::string>()> watched) override {
    std::lock_guard<std::mutex> lock(listener_mu_);
    watched_ = std::move(watched);
  }

  absl::StatusOr<v1::Job> CreateJob(const std::string& id, const v1::JobSpec& spec,
                                    const std::string& request_id, int max_queued,
                                    const std::string& creator, bool* created) override {
    *created = false;
    auto existing = [&](pqxx::work& w) -> std::optional<absl::StatusOr<v1::Job>> {
      if (request_id.empty()) return std::nullopt;
      auto r = w.exec_params("SELECT job FROM jobs WHERE request_id=$1", request_id);
      if (r.empty()) return std::nullopt;
      return ParseJob(r[0][0]);
    };
    bool made = false;
    auto out = Run<
        absl::StatusOr<v1::Job>>("creating a job", [&](pqxx::work& w) -> absl::StatusOr<v1::Job> {
      made = false;
      if (auto e = existing(w)) return *e;
      const int64_t queued =
          w.exec_params("SELECT COUNT(*) FROM jobs WHERE state=$1", int{v1::QUEUED})[0][0]
              .as<int64_t>();
      if (auto s = CheckQueueRoom(queued, max_queued); !s.ok()) return s;
      TxEvents tx;
      v1::Job job = NewQueuedJob(id, spec, request_id, creator, &tx.events);
      // Two replicas inserting one request_id at once: the second waits for the first to
      // commit, inserts nothing and returns the first's job below.
      auto ins = w.exec_params(
          "INSERT INTO jobs(id, request_id, state, volume, job, creator) "
          "VALUES($1,NULLIF($2,''),$3,$4,$5,$6) ON CONFLICT (request_id) DO NOTHING RETURNING ord",
          id, request_id, int{v1::QUEUED}, spec.volume(), Bytes(job), creator);
      if (ins.empty()) {
        if (auto e = existing(w)) return *e;
        return absl::AbortedError("job store: request_id conflict without a row; retry");
      }
      tx.Save(w);
      made = true;
      return job;
    });
    *created = out.ok() && made;
    return out;
  }

  absl::StatusOr<v1::Job> GetJob(const std::string& id) override {
    return Read<absl::StatusOr<v1::Job>>("reading a job",
                                         [&](pqxx::work& w) { return LoadJob(w, id, false); });
  }

  absl::StatusOr<JobPage> ListJobs(const std::vector<v1::JobState>& states,
                                   const std::string& creator, int page_size,
                                   const std::string& page_token) override {
    auto before = DecodePageToken(page_token);
    if (!before.ok()) return before.status();
    const int limit = ClampPageSize(page_size);
    std::vector<std::string> parts;
    for (auto s : states) parts.push_back(absl::StrCat(static_cast<int>(s)));
    return Read<absl::StatusOr<JobPage>>(
        "listing jobs", [&](pqxx::work& w) -> absl::StatusOr<JobPage> {
          auto r = w.exec_params(
              "SELECT ord, job FROM jobs WHERE ord < $1 AND ($2 OR state = ANY($3::int[])) "
              "AND ($5 = '' OR creator = $5) ORDER BY ord DESC LIMIT $4",
              *before, states.empty(), TextArray(parts), limit + 1, creator);
          JobPage page;
          int64_t last_ord = 0;
          for (const auto& row : r) {
            if (static_cast<int>(page.jobs.size()) == limit) {
              page.next_page_token = EncodePageToken(last_ord);
              break;
            }
            last_ord = row[0].as<int64_t>();
            auto job = ParseJob(row[1]);
            if (!job.ok()) return job.status();
            page.jobs.push_back(std::move(*job));
          }
          return page;
        });
  }

  absl::StatusOr<int64_t> CountJobs(v1::JobState state) override {
    return Read<absl::StatusOr<int64_t>>(
        "counting jobs", [&](pqxx::work& w) -> absl::StatusOr<int64_t> {
          return w.exec_params("SELECT COUNT(*) FROM jobs WHERE state=$1", int{state})[0][0]
              .as<int64_t>();
        });
  }

  absl::StatusOr<std::optional<Claim>> ClaimNext(const std::string& owner,
                                                 int64_t lease_ms) override {
    using Out = absl::StatusOr<std::optional<Claim>>;
    return Run<Out>("claiming a job", [&](pqxx::work& w) -> Out {
      auto r = w.exec_params(
          "SELECT job, lease_epoch FROM jobs WHERE state=$1 ORDER BY ord LIMIT 1 "
          "FOR UPDATE SKIP LOCKED",
          int{v1::QUEUED});
      if (r.empty()) return std::optional<Claim>();
      auto job = ParseJob(r[0][0]);
      if (!job.ok()) return job.status();
      Claim claim;
      claim.lease = {job->name().substr(5), owner, r[0][1].as<int64_t>() + 1};
      TxEvents tx;
      StartAttempt(*job, &tx.events);
      w.exec_params(
          "UPDATE jobs SET state=$1, lease_owner=$2, "
          "lease_expiry=clock_timestamp() + $3 * interval '1 millisecond', lease_epoch=$4, "
          "cancel_requested=FALSE, job=$5 WHERE id=$6",
          int{v1::RUNNING}, owner, lease_ms, claim.lease.epoch, Bytes(*job), claim.lease.job_id);
      tx.Save(w);
      claim.job = std::move(*job);
      return std::optional<Claim>(std::move(claim));
    });
  }

  absl::Status RenewLease(const Lease& lease, int64_t lease_ms) override {
    return Run<absl::Status>("renewing a lease", [&](pqxx::work& w) -> absl::Status {
      auto r = w.exec_params(
          "UPDATE jobs SET lease_expiry=clock_timestamp() + $1 * interval '1 millisecond' "
          "WHERE id=$2 AND state=$3 AND lease_owner=$4 AND lease_epoch=$5",
          lease_ms, lease.job_id, int{v1::RUNNING}, lease.owner, lease.epoch);
      if (r.affected_rows() != 1) {
        return absl::FailedPreconditionError(absl::StrCat("jobs/", lease.job_id,
                                                          " is no longer leased to ", lease.owner,
                                                          " epoch ", lease.epoch));
      }
      return absl::OkStatus();
    });
  }

  absl::Status AppendProgress(const Lease& lease, const v1::Progress& progress) override {
    return Run<absl::Status>("storing progress", [&](pqxx::work& w) -> absl::Status {
      auto job = LoadHeld(w, lease);
      if (!job.ok()) return job.status();
      TxEvents tx;
      RecordProgress(*job, progress, &tx.events);
      w.exec_params("UPDATE jobs SET job=$1 WHERE id=$2", Bytes(*job), lease.job_id);
      tx.Save(w);
      return absl::OkStatus();
    });
  }

  absl::StatusOr<v1::Job> Finish(const Lease& lease, v1::JobState state,
                                 const v1::Job& outcome) override {
    return Run<absl::StatusOr<v1::Job>>("finishing a job",
                                        [&](pqxx::work& w) -> absl::StatusOr<v1::Job> {
                                          auto job = LoadHeld(w, lease);
                                          if (!job.ok()) return job.status();
                                          TxEvents tx;
                                          FinishAttempt(*job, state, outcome, &tx.events);
                                          SaveJob(w, *job, false);
                                          tx.Save(w);
                                          return *job;
                                        });
  }

  absl::StatusOr<v1::Job> Requeue(const Lease& lease, const std::string& reason) override {
    return Run<absl::StatusOr<v1::Job>>("requeueing a job",
                                        [&](pqxx::work& w) -> absl::StatusOr<v1::Job> {
                                          auto job = LoadHeld(w, lease);
                                          if (!job.ok()) return job.status();
                                          TxEvents tx;
                                          RequeueAttempt(*job, reason, &tx.events);
                                          SaveJob(w, *job, false);
                                          tx.Save(w);
                                          return *job;
                                        });
  }

  absl::StatusOr<Recovered> RecoverLeases(bool all, int max_attempts) override {
    return Run<absl::StatusOr<Recovered>>(
        "recovering lapsed leases", [&](pqxx::work& w) -> absl::StatusOr<Recovered> {
          // SKIP LOCKED: the reapers of several replicas split the lapsed jobs instead of queueing
          // behind each other, and a job whose holder is finishing it right now is left alone.
          auto r = w.exec_params(
              "SELECT job, cancel_requested FROM jobs WHERE state=$1 AND "
              "($2 OR lease_expiry < clock_timestamp()) FOR UPDATE SKIP LOCKED",
              int{v1::RUNNING}, all);
          Recovered out;
          TxEvents tx;
          for (const auto& row : r) {
            auto parsed = ParseJob(row[0]);
            if (!parsed.ok()) return parsed.status();
            v1::Job& job = *parsed;
            const bool requeued = ResolveLapsedLease(job, row[1].as<bool>(), max_attempts,
                                                     &tx.events) == LapsedLease::kRequeued;
            (requeued ? out.requeued : out.failed).push_back(JobIdOf(job));
            SaveJob(w, job, false);
          }
          tx.Save(w);
          return out;
        });
  }

  absl::StatusOr<v1::Job> Cancel(const std::string& id) override {
    return Run<absl::StatusOr<v1::Job>>(
        "cancelling a job", [&](pqxx::work& w) -> absl::StatusOr<v1::Job> {
          auto job = LoadJob(w, id, true);
          if (!job.ok()) return job.status();
          if (job->state() == v1::QUEUED) {
            TxEvents tx;
            CancelQueued(*job, &tx.events);
            SaveJob(w, *job, false);
            tx.Save(w);
          } else if (job->state() == v1::RUNNING) {
            w.exec_params("UPDATE jobs SET cancel_requested=TRUE WHERE id=$1", id);
          }
          return *job;
        });
  }

  absl::StatusOr<bool> CancelRequested(const std::string& id) override {
    return Read<absl::StatusOr<bool>>(
        "reading a cancel request", [&](pqxx::work& w) -> absl::StatusOr<bool> {
          auto r = w.exec_params("SELECT cancel_requested FROM jobs WHERE id=$1", id);
          if (r.empty()) return absl::NotFoundError(absl::StrCat("job ", id, " not found"));
          return r[0][0].as<bool>();
        });
  }

  absl::StatusOr<v1::Job> Retry(const std::string& id, int max_queued) override {
    return Run<absl::StatusOr<v1::Job>>(
        "retrying a job", [&](pqxx::work& w) -> absl::StatusOr<v1::Job> {
          auto job = LoadJob(w, id, true);
          if (!job.ok()) return job.status();
          if (auto s = CheckRetryable(*job); !s.ok()) return s;
          const int64_t queued =
              w.exec_params("SELECT COUNT(*) FROM jobs WHERE state=$1", int{v1::QUEUED})[0][0]
                  .as<int64_t>();
          if (auto s = CheckQueueRoom(queued, max_queued); !s.ok()) return s;
          TxEvents tx;
          ResetForRetry(*job, &tx.events);
          SaveJob(w, *job, false);
          tx.Save(w);
          return *job;
        });
  }

  absl::Status DeleteJob(const std::string& id) override {
    return Run<absl::Status>("deleting a job", [&](pqxx::work& w) -> absl::Status {
      auto job = LoadJob(w, id, true);
      if (!job.ok()) return job.status();
      if (auto s = CheckDeletable(*job); !s.ok()) return s;
      w.exec_params("DELETE FROM events WHERE job_id=$1", id);
      w.exec_params("DELETE FROM jobs WHERE id=$1", id);
      return absl::OkStatus();
    });
  }

  absl::StatusOr<std::vector<v1::JobEvent>> ListEvents(const std::string& id, int64_t after,
                                                       int limit) override {
    using Out = absl::StatusOr<std::vector<v1::JobEvent>>;
    return Read<Out>("listing events", [&](pqxx::work& w) -> Out {
      auto r =
          w.exec_params("SELECT event FROM events WHERE job_id=$1 AND seq>$2 ORDER BY seq LIMIT $3",
                        id, after, limit);
      std::vector<v1::JobEvent> out;
      for (const auto& row : r) {
        v1::JobEvent ev;
        if (!ev.ParseFromString(FieldBytes(row[0]))) {
          return absl::DataLossError("job store: bad event row");
        }
        out.push_back(std::move(ev));
      }
      return out;
    });
  }

  absl::StatusOr<v1::Volume> CreateVolume(const std::string& id, const v1::Volume& volume,
                                          const std::string& request_id,
                                          const std::string& content_key, bool* created) override {
    *created = false;
    bool made = false;
    auto out = Run<absl::StatusOr<v1::Volume>>(
        "creating a volume", [&](pqxx::work& w) -> absl::StatusOr<v1::Volume> {
          made = false;
          auto existing = [&]() -> std::optional<absl::StatusOr<v1::Volume>> {
            if (!request_id.empty()) {
              auto r = w.exec_params("SELECT volume FROM volumes WHERE request_id=$1", request_id);
              if (!r.empty()) return ParseVolume(r[0][0]);
            }
            if (!content_key.empty()) {
              auto r =
                  w.exec_params("SELECT volume FROM volumes WHERE creator=$1 AND content_key=$2",
                                volume.creator(), content_key);
              if (!r.empty()) return ParseVolume(r[0][0]);
            }
            return std::nullopt;
          };
          if (auto e = existing()) return *e;
          // Without a conflict target: a concurrent create of the same request id or of the
          // same creator and content (another replica's) leaves its row to be answered.
          auto ins = w.exec_params(
              "INSERT INTO volumes(id, request_id, volume, creator, content_key) "
              "VALUES($1,NULLIF($2,''),$3,$4,NULLIF($5,'')) ON CONFLICT DO NOTHING RETURNING ord",
              id, request_id, Bytes(volume), volume.creator(), content_key);
          if (ins.empty()) {
            if (auto e = existing()) return *e;
            return absl::AbortedError("job store: volume conflict without a row; retry");
          }
          for (const auto& f : volume.files()) {
            // The catalog checked the names; a store never trusts its caller with substr.
            if (!absl::StartsWith(f.blob(), "blobs/")) {
              return absl::InvalidArgumentError(absl::StrCat("job store: volume file ", f.path(),
                                                             ": blob '", f.blob(),
                                                             "' is not 'blobs/{sha256}'"));
            }
            w.exec_params(
                "INSERT INTO volume_blobs(volume_id, sha256) VALUES($1,$2) ON CONFLICT DO NOTHING",
                id, f.blob().substr(6));
          }
          made = true;
          return volume;
        });
    *created = out.ok() && made;
    return out;
  }

  absl::StatusOr<v1::Volume> GetVolume(const std::string& id) override {
    return Read<absl::StatusOr<v1::Volume>>(
        "reading a volume", [&](pqxx::work& w) -> absl::StatusOr<v1::Volume> {
          auto r = w.exec_params("SELECT volume FROM volumes WHERE id=$1", id);
          if (r.empty()) return absl::NotFoundError(absl::StrCat("volumes/", id, " not found"));
          return ParseVolume(r[0][0]);
        });
  }

  absl::StatusOr<VolumePage> ListVolumes(const std::string& creator, int page_size,
                                         const std::string& page_token) override {
    auto before = DecodePageToken(page_token);
    if (!before.ok()) return before.status();
    const int limit = ClampPageSize(page_size);
    return Read<absl::StatusOr<VolumePage>>(
        "listing volumes", [&](pqxx::work& w) -> absl::StatusOr<VolumePage> {
          auto r = w.exec_params(
              "SELECT ord, volume FROM volumes WHERE ord < $1 AND ($3 = '' OR creator = $3) "
              "ORDER BY ord DESC LIMIT $2",
              *before, limit + 1, creator);
          VolumePage page;
          int64_t last_ord = 0;
          for (const auto& row : r) {
            if (static_cast<int>(page.volumes.size()) == limit) {
              page.next_page_token = EncodePageToken(last_ord);
              break;
            }
            last_ord = row[0].as<int64_t>();
            auto v = ParseVolume(row[1]);
            if (!v.ok()) return v.status();
            page.volumes.push_back(std::move(*v));
          }
          return page;
        });
  }

  absl::Status DeleteVolume(const std::string& id) override {
    return Run<absl::Status>("deleting a volume", [&](pqxx::work& w) -> absl::Status {
      auto v = w.exec_params("SELECT 1 FROM volumes WHERE id=$1 FOR UPDATE", id);
      if (v.empty()) return absl::NotFoundError(absl::StrCat("volumes/", id, " not found"));
      // A queued or running job reads the volume as its input or its label map (the label map
      // lives only in the stored spec, so the active jobs' specs are read: at most max_queued
      // plus the running ones).
      const std::string name = absl::StrCat("volumes/", id);
      auto active = w.exec_params("SELECT job FROM jobs WHERE state IN ($1,$2)", int{v1::QUEUED},
                                  int{v1::RUNNING});
      int64_t readers = 0;
      for (const auto& row : active) {
        auto job = ParseJob(row[0]);
        if (!job.ok()) return job.status();
        if (job->spec().volume() == name || job->spec().label_map() == name) ++readers;
      }
      if (readers > 0) {
        return absl::FailedPreconditionError(absl::StrCat(
            name, " is read by ", readers, " queued or running job(s) (as volume or label map)"));
      }
      w.exec_params("DELETE FROM volumes WHERE id=$1", id);
      w.exec_params("DELETE FROM volume_blobs WHERE volume_id=$1", id);
      return absl::OkStatus();
    });
  }

  absl::StatusOr<bool> BlobInUse(const std::string& sha256) override {
    return Read<absl::StatusOr<bool>>(
        "checking blob use", [&](pqxx::work& w) -> absl::StatusOr<bool> {
          return !w.exec_params(
                       "SELECT 1 FROM volume_blobs WHERE sha256=$1 UNION ALL "
                       "SELECT 1 FROM dicom_instances WHERE sha256=$1 LIMIT 1",
                       sha256)
                      .empty();
        });
  }

  absl::Status PutDicomInstance(const DicomInstanceRecord& r) override {
    return Run<absl::Status>("storing a DICOM instance", [&](pqxx::work& w) -> absl::Status {
      // The row lock holds a concurrent store of the same key until this one commits.
      auto held = w.exec_params(
          "SELECT sha256 FROM dicom_instances WHERE calling_ae=$1 AND sop_instance_uid=$2 "
          "FOR UPDATE",
          r.calling_ae, r.sop_instance_uid);
      if (!held.empty() && held[0][0].as<std::string>() != r.sha256) {
        return absl::AlreadyExistsError(
            absl::StrCat("SOP instance ", r.sop_instance_uid, " from ", r.calling_ae,
                         " is already held with other bytes (sha256 ", held[0][0].as<std::string>(),
                         ", now ", r.sha256, ")"));
      }
      // Delete + insert (not ON CONFLICT UPDATE): a re-sent instance gets a new ord, so the
      // series order stays "as last received", as in the SQLite store.
      w.exec_params("DELETE FROM dicom_instances WHERE calling_ae=$1 AND sop_instance_uid=$2",
                    r.calling_ae, r.sop_instance_uid);
      w.exec_params(
          "INSERT INTO dicom_instances(sop_instance_uid, series_instance_uid, sha256, calling_ae, "
          "called_ae, received_ms, aborted_ms, size_bytes, association_id) "
          "VALUES($1,$2,$3,$4,$5,$6,$7,$8,$9)",
          r.sop_instance_uid, r.series_instance_uid, r.sha256, r.calling_ae, r.called_ae,
          r.received_ms, r.aborted_ms, r.size_bytes, r.association_id);
      return absl::OkStatus();
    });
  }

  absl::StatusOr<std::vector<DicomInstanceRecord>> ListDicomInstances() override {
    using Out = absl::StatusOr<std::vector<DicomInstanceRecord>>;
    return Read<Out>("listing DICOM instances", [&](pqxx::work& w) -> Out {
      return Instances(w.exec(absl::StrCat(kInstanceColumns, "ORDER BY ord")));
    });
  }

  absl::Status MarkDicomSeriesAborted(const std::string& calling_ae,
                                      const std::string& series_instance_uid,
                                      int64_t aborted_ms) override {
    return Run<absl::Status>("marking a DICOM series aborted", [&](pqxx::work& w) -> absl::Status {
      w.exec_params(
          "UPDATE dicom_instances SET aborted_ms=$1 WHERE calling_ae=$2 AND series_instance_uid=$3",
          aborted_ms, calling_ae, series_instance_uid);
      return absl::OkStatus();
    });
  }

  absl::Status PutDicomSeries(const DicomSeriesRecord& r,
                              const std::vector<std::string>& consumed) override {
    return Run<absl::Status>("storing a DICOM series outcome", [&](pqxx::work& w) -> absl::Status {
      w.exec_params(
          "INSERT INTO dicom_series(instance_set, series_instance_uid, job, reason, route, "
          "results_pending, send_status, update_ms, state, calling_ae, called_ae, "
          "instance_count, first_received_ms, last_received_ms, receive_key, association_id) "
          "VALUES($1,$2,$3,$4,$5,$6,$7,$8,$9,$10,$11,$12,$13,$14,$15,$16) "
          "ON CONFLICT(receive_key) DO UPDATE SET instance_set=$1, job=$3, reason=$4, route=$5, "
          "results_pending=$6, send_status=$7, update_ms=$8, state=$9, calling_ae=$10, "
          "called_ae=$11, instance_count=$12, first_received_ms=$13, last_received_ms=$14, "
          "association_id=$16",
          r.instance_set, r.series_instance_uid, r.job, r.reason, r.route, r.results_pending,
          r.send_status, r.update_ms, static_cast<int>(r.state), r.calling_ae, r.called_ae,
          r.instance_count, r.first_received_ms, r.last_received_ms, r.receive_key,
          r.association_id);
      for (const auto& uid : consumed) {
        w.exec_params("DELETE FROM dicom_instances WHERE calling_ae=$1 AND sop_instance_uid=$2",
                      r.calling_ae, uid);
      }
      return absl::OkStatus();
    });
  }

  absl::StatusOr<std::vector<DicomSeriesRecord>> ListDicomSeries(bool pending_only,
                                                                 int limit) override {
    using Out = absl::StatusOr<std::vector<DicomSeriesRecord>>;
    return Read<Out>("listing DICOM series", [&](pqxx::work& w) -> Out {
      std::vector<DicomSeriesRecord> out;
      for (const auto& row : w.exec_params(
               absl::StrCat("SELECT instance_set, series_instance_uid, job, reason, route, "
                            "results_pending, send_status, update_ms, state, calling_ae, "
                            "called_ae, instance_count, first_received_ms, last_received_ms, "
                            "receive_key, association_id FROM dicom_series ",
                            pending_only ? "WHERE results_pending " : "",
                            "ORDER BY ord DESC LIMIT $1"),
               limit)) {
        DicomSeriesRecord r;
        r.instance_set = row[0].as<std::string>();
        r.series_instance_uid = row[1].as<std::string>();
        r.job = row[2].as<std::string>();
        r.reason = row[3].as<std::string>();
        r.route = row[4].as<std::string>();
        r.results_pending = row[5].as<bool>();
        r.send_status = row[6].as<std::string>();
        r.update_ms = row[7].as<int64_t>();
        r.state = static_cast<v1::ReceivedSeries::State>(row[8].as<int>());
        r.calling_ae = row[9].as<std::string>();
        r.called_ae = row[10].as<std::string>();
        r.instance_count = row[11].as<int>();
        r.first_received_ms = row[12].as<int64_t>();
        r.last_received_ms = row[13].as<int64_t>();
        r.receive_key = row[14].as<std::string>();
        r.association_id = row[15].as<std::string>();
        out.push_back(std::move(r));
      }
      return out;
    });
  }

  absl::Status Ping() override {
    std::unique_ptr<pqxx::connection> conn;
    try {
      conn = pool_.Acquire();
      pqxx::nontransaction n(*conn);
      n.exec("SELECT 1");
      pool_.Release(std::move(conn), false);
      return absl::OkStatus();
    } catch (const std::exception& e) {
      if (conn) pool_.Release(std::move(conn), true);
      return absl::UnavailableError(absl::StrCat("job store: PostgreSQL unreachable: ", e.what()));
    }
  }

  absl::StatusOr<std::vector<DicomInstanceRecord>> RemoveDicomInstances(
      const std::string& calling_ae, const std::string& series_instance_uid) override {
    using Out = absl::StatusOr<std::vector<DicomInstanceRecord>>;
    return Run<Out>("removing DICOM instances", [&](pqxx::work& w) -> Out {
      return Instances(w.exec_params(
          "DELETE FROM dicom_instances WHERE calling_ae=$1 AND series_instance_uid=$2 "
          "RETURNING series_instance_uid, sop_instance_uid, sha256, calling_ae, called_ae, "
          "received_ms, aborted_ms, size_bytes, association_id",
          calling_ae, series_instance_uid));
    });
  }

  absl::StatusOr<int64_t> DicomWaitingBytes(const std::string& calling_ae) override {
    return Read<absl::StatusOr<int64_t>>(
        "summing a sender's DICOM instances", [&](pqxx::work& w) -> absl::StatusOr<int64_t> {
          return w
              .exec_params1(
                  "SELECT COALESCE(SUM(size_bytes), 0)::BIGINT FROM dicom_instances "
                  "WHERE calling_ae=$1",
                  calling_ae)[0]
              .as<int64_t>();
        });
  }

 private:
  // Run for a body that only reads: a connection lost during its commit is retried too, since
  // whether a read-only transaction committed changes nothing (a watcher's listing of events
  // failed with "the outcome is unknown" when PostgreSQL restarted under load).
  template <typename R, typename F>
  R Read(const char* what, F&& body) {
    return Run<R>(what, std::forward<F>(body), /*read_only=*/true);
  }

  // Runs `body` in a transaction on a pooled connection and commits when it returns OK. A lost
  // connection (before the commit) is retried on a new one until reconnect_timeout; `body` must
  // therefore only write to the transaction and to state it resets itself.
  template <typename R, typename F>
  R Run(const char* what, F&& body, bool read_only = false) {
    const auto deadline = std::chrono::steady_clock::now() + options_.reconnect_timeout;
    std::chrono::milliseconds backoff(50);
    for (int attempt = 0;; ++attempt) {
      std::unique_ptr<pqxx::connection> conn;
      std::string error;
      try {
        conn = pool_.Acquire();
        pqxx::work w(*conn);
        R out = body(w);
        if (StatusOf(out).ok()) w.commit();
        pool_.Release(std::move(conn), false);
        return out;
      } catch (const pqxx::in_doubt_error& e) {
        if (!read_only) {
          if (conn) pool_.Release(std::move(conn), true);
          return absl::UnavailableError(absl::StrCat("job store: ", what,
                                                     ": the connection was lost during commit; "
                                                     "the outcome is unknown (",
                                                     e.what(), ")"));
        }
        error = e.what();  // released and retried below
      } catch (const pqxx::broken_connection& e) {
        error = e.what();
      } catch (const pqxx::sql_error& e) {
        // 40001 serialization failure, 40P01 deadlock: run the transaction again. 57P01 etc.
        // (admin shutdown) and 08xxx (connection exceptions) mean the server went away.
        // No SQLSTATE or a closed connection: the server went away mid-statement.
        const std::string& state = e.sqlstate();
        if (state.empty() || (conn && !conn->is_open()) || state == "40001" || state == "40P01" ||
            state.rfind("57P", 0) == 0 || state.rfind("08", 0) == 0) {
          error = e.what();
        } else {
          if (conn) pool_.Release(std::move(conn), !conn->is_open());
          return absl::InternalError(absl::StrCat("job store: ", what, ": ", e.what()));
        }
      } catch (const std::exception& e) {
        // pqxx::failure without a connection error (e.g. "connection lost" as a plain
        // failure) and anything else: treat the connection as suspect and retry.
        error = e.what();
      }
      if (conn) pool_.Release(std::move(conn), true);
      if (std::chrono::steady_clock::now() + backoff > deadline || stop_) {
        return absl::UnavailableError(
            absl::StrCat("job store: ", what, ": PostgreSQL unreachable: ", error));
      }
      if (attempt == 0) spdlog::warn("job store: {}: {}; retrying", what, error);
      std::this_thread::sleep_for(backoff);
      backoff = std::min(backoff * 2, std::chrono::milliseconds(1000));
    }
  }

  static absl::Status StatusOf(const absl::Status& s) { return s; }
  template <typename T>
  static absl::Status StatusOf(const absl::StatusOr<T>& s) {
    return s.status();
  }

  static absl::StatusOr<v1::Job> LoadJob(pqxx::work& w, const std::string& id, bool for_update) {
    auto r = w.exec_params(for_update ? "SELECT job FROM jobs WHERE id=$1 FOR UPDATE"
                                      : "SELECT job FROM jobs WHERE id=$1",
                           id);
    if (r.empty()) return absl::NotFoundError(absl::StrCat("jobs/", id, " not found"));
    return ParseJob(r[0][0]);
  }

  // The job, locked, if RUNNING under exactly `lease` (owner and epoch).
  static absl::StatusOr<v1::Job> LoadHeld(pqxx::work& w, const Lease& lease) {
    auto r = w.exec_params(
        "SELECT job, state, lease_owner, lease_epoch FROM jobs WHERE id=$1 FOR UPDATE",
        lease.job_id);
    if (r.empty()) return absl::NotFoundError(absl::StrCat("jobs/", lease.job_id, " not found"));
    const auto& row = r[0];
    if (row[1].as<int>() != v1::RUNNING || row[2].is_null() ||
        row[2].as<std::string>() != lease.owner || row[3].as<int64_t>() != lease.epoch) {
      return absl::FailedPreconditionError(absl::StrCat("jobs/", lease.job_id,
                                                        " is not running under lease ", lease.owner,
                                                        " epoch ", lease.epoch));
    }
    return ParseJob(row[0]);
  }

  // Writes the job row; the lease is dropped (every caller leaves RUNNING or never had one).
  static void SaveJob(pqxx::work& w, const v1::Job& job, bool keep_cancel) {
    w.exec_params(
        "UPDATE jobs SET state=$1, lease_owner=NULL, lease_expiry=NULL, "
        "cancel_requested=(cancel_requested AND $2), job=$3 WHERE id=$4",
        int{job.state()}, keep_cancel, Bytes(job), job.name().substr(5));
  }

  // --- the event feed ---------------------------------------------------------------------

  class Receiver : public pqxx::notification_receiver {
   public:
    Receiver(pqxx::connection_base& c, std::map<std::string, int64_t>* pending)
        : pqxx::notification_receiver(c, kChannel), pending_(pending) {}
    void operator()(const std::string& payload, int) override {
      const size_t colon = payload.rfind(':');
      int64_t seq = 0;
      if (colon == std::string::npos || !absl::SimpleAtoi(payload.substr(colon + 1), &seq)) return;
      auto [it, inserted] = pending_->emplace(payload.substr(0, colon), seq);
      if (!inserted) it->second = std::min(it->second, seq);
    }

   private:
    std::map<std::string, int64_t>* pending_;  // job -> lowest notified sequence
  };

  void ListenLoop() {
    std::chrono::milliseconds backoff(50);
    bool first = true;
    while (!stop_) {
      try {
        auto conn = ConnectionPool::Connect(dsn_, options_.application_name + " (listen)");
        std::map<std::string, int64_t> pending;
        Receiver receiver(*conn, &pending);
        conn->get_notifs();  // the LISTEN is in effect from here on
        {
          std::lock_guard<std::mutex> lock(listening_mu_);
          listening_ = true;
        }
        listening_cv_.notify_all();
        if (!first) {
          spdlog::info("job store: event feed reconnected; re-reading watched jobs");
          Resync(*conn);
        }
        first = false;
        backoff = std::chrono::milliseconds(50);
        auto last_ping = std::chrono::steady_clock::now();
        while (!stop_) {
          conn->await_notification(0, 200 * 1000);
          conn->get_notifs();
          if (!pending.empty()) {
            std::map<std::string, int64_t> batch;
            batch.swap(pending);
            Deliver(*conn, batch);
            last_ping = std::chrono::steady_clock::now();
          } else if (std::chrono::steady_clock::now() - last_ping > std::chrono::seconds(1)) {
            // An idle socket does not notice a dead server: ask something cheap.
            pqxx::nontransaction n(*conn);
            n.exec("SELECT 1");
            last_ping = std::chrono::steady_clock::now();
          }
        }
      } catch (const std::exception& e) {
        if (stop_) break;
        spdlog::warn("job store: event feed lost ({}); reconnecting", e.what());
        std::this_thread::sleep_for(backoff);
        backoff = std::min(backoff * 2, std::chrono::milliseconds(1000));
      }
    }
  }

  // Reads and delivers the events of the notified jobs above what was delivered. `notified`:
  // job -> lowest sequence notified (for a job not followed yet, reading starts there).
  void Deliver(pqxx::connection& conn, const std::map<std::string, int64_t>& notified) {
    std::vector<std::string> ids, afters;
    for (const auto& [id, seq] : notified) {
      auto it = delivered_.find(id);
      ids.push_back(id);
      afters.push_back(absl::StrCat(it != delivered_.end() ? it->second : seq - 1));
    }
    if (!ids.empty()) ReadAndPublish(conn, ids, afters);
  }

  // Re-reads every job followed or watched here (after a reconnect nothing was missed).
  void Resync(pqxx::connection& conn) {
    std::set<std::string> jobs;
    for (const auto& [id, seq] : delivered_) jobs.insert(id);
    std::function<std::vector<std::string>()> watched;
    {
      std::lock_guard<std::mutex> lock(listener_mu_);
      watched = watched_;
    }
    if (watched) {
      for (auto& id : watched()) jobs.insert(std::move(id));
    }
    std::vector<std::string> ids, afters;
    for (const auto& id : jobs) {
      auto it = delivered_.find(id);
      ids.push_back(id);
      afters.push_back(absl::StrCat(it != delivered_.end() ? it->second : 0));
    }
    if (!ids.empty()) ReadAndPublish(conn, ids, afters);
  }

  void ReadAndPublish(pqxx::connection& conn, const std::vector<std::string>& ids,
                      const std::vector<std::string>& afters) {
    pqxx::nontransaction n(conn);
    auto r = n.exec_params(
        "SELECT e.job_id, e.event FROM events e "
        "JOIN unnest($1::text[], $2::bigint[]) AS w(id, after) "
        "ON e.job_id = w.id AND e.seq > w.after ORDER BY e.job_id, e.seq",
        TextArray(ids), TextArray(afters));
    EventListener listener;
    {
      std::lock_guard<std::mutex> lock(listener_mu_);
      listener = listener_;
    }
    for (const auto& row : r) {
      const std::string id = row[0].as<std::string>();
      v1::JobEvent ev;
      if (!ev.ParseFromString(FieldBytes(row[1]))) {
        spdlog::error("job store: bad event row of job {}", id);
        continue;
      }
      auto it = delivered_.find(id);
      if (it != delivered_.end() && ev.sequence() <= it->second) continue;
      if (listener) listener(id, ev);
      delivered_[id] = ev.sequence();
      if (ev.has_state_change() && IsFinal(ev.state_change().state())) {
        finals_.emplace_back(std::chrono::steady_clock::now(), id, ev.sequence());
      }
    }
    // Bounded memory. A final job is forgotten a minute after its last event (notifications
    // read ahead of arrive well before that; a job retried later is read from its new
    // notification on). Jobs that never end (deleted while followed) are dropped wholesale.
    const auto cutoff = std::chrono::steady_clock::now() - std::chrono::minutes(1);
    while (!finals_.empty() && std::get<0>(finals_.front()) < cutoff) {
      const auto& [t, id, seq] = finals_.front();
      auto it = delivered_.find(id);
      if (it != delivered_.end() && it->second == seq) delivered_.erase(it);
      finals_.pop_front();
    }
    if (delivered_.size() > 100000) delivered_.clear();
  }

  const std::string dsn_;
  const PostgresStoreOptions options_;
  ConnectionPool pool_;
  std::atomic<bool> stop_{false};
  std::thread listen_thread_;
  std::mutex listening_mu_;
  std::condition_variable listening_cv_;
  bool listening_ = false;
  std::mutex listener_mu_;
  EventListener listener_;
  std::function<std::vector<std::string>()> watched_;
  // Listen thread only: job -> newest delivered sequence; final events by delivery time.
  std::map<std::string, int64_t> delivered_;
  std::deque<std::tuple<std::chrono::steady_clock::time_point, std::string, int64_t>> finals_;
};

}  // namespace

absl::StatusOr<std::unique_ptr<JobStore>> OpenPostgresJobStore(
    const std::string& dsn, const PostgresStoreOptions& options) {
  auto store = std::make_unique<PostgresJobStore>(dsn, options);
  if (absl::Status s = store->Migrate(); !s.ok()) return s;
  if (absl::Status s = store->StartListening(); !s.ok()) return s;
  return std::unique_ptr<JobStore>(std::move(store));
}

}  // namespace decima::server
