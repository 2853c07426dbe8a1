// The embedded JobStore: one SQLite database in WAL mode. Each job row keeps a few indexed
// columns (state, lease, request id) beside the serialized decima.v1.Job, which is the source
// of truth for everything else; events are rows keyed by (job, sequence). One connection
// guarded by a mutex: the store serves one process (the data dir is locked by the server).
#include <google/protobuf/util/time_util.h>
#include <sqlite3.h>

#include <chrono>
#include <mutex>
#include <utility>

#include "absl/strings/match.h"
#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"
#include "server/store/job_lifecycle.h"
#include "server/store/job_store.h"

// Commits `tx` or returns its error.
#define DECIMA_TX_COMMIT(tx)                 \
  do {                                       \
    absl::Status tx_status_ = (tx).Commit(); \
    if (!tx_status_.ok()) return tx_status_; \
  } while (0)
#define DECIMA_RETURN_IF_ERROR_LOCAL(expr) \
  do {                                     \
    absl::Status st_ = (expr);             \
    if (!st_.ok()) return st_;             \
  } while (0)

namespace decima::server {
namespace {

using google::protobuf::util::TimeUtil;

int64_t NowMs() {
  return std::chrono::duration_cast<std::chrono::milliseconds>(
             std::chrono::system_clock::now().time_since_epoch())
      .count();
}

// A prepared statement; binds by 1-based index, resets on destruction.
class Stmt {
 public:
  Stmt(sqlite3* db, const char* sql) : db_(db) {
    rc_ = sqlite3_prepare_v2(db, sql, -1, &stmt_, nullptr);
  }
  ~Stmt() { sqlite3_finalize(stmt_); }
  bool ok() const { return rc_ == SQLITE_OK; }
  Stmt& Bind(int i, int64_t v) {
    sqlite3_bind_int64(stmt_, i, v);
    return *this;
  }
  Stmt& Bind(int i, const std::string& v) {
    sqlite3_bind_text(stmt_, i, v.data(), static_cast<int>(v.size()), SQLITE_TRANSIENT);
    return *this;
  }
  Stmt& BindBlob(int i, const std::string& v) {
    sqlite3_bind_blob(stmt_, i, v.data(), static_cast<int>(v.size()), SQLITE_TRANSIENT);
    return *this;
  }
  Stmt& BindNull(int i) {
    sqlite3_bind_null(stmt_, i);
    return *this;
  }
  // SQLITE_ROW, SQLITE_DONE or an error code.
  int Step() { return sqlite3_step(stmt_); }
  int64_t Int(int col) { return sqlite3_column_int64(stmt_, col); }
  std::string Text(int col) {
    const void* p = sqlite3_column_blob(stmt_, col);
    int n = sqlite3_column_bytes(stmt_, col);
    return p ? std::string(static_cast<const char*>(p), static_cast<size_t>(n)) : std::string();
  }
  absl::Status Error(const char* what) const {
    return absl::InternalError(absl::StrCat("job store: ", what, ": ", sqlite3_errmsg(db_)));
  }

 private:
  sqlite3* db_;
  sqlite3_stmt* stmt_ = nullptr;
  int rc_;
};

// One keyset page from `q`, whose rows are (ord, serialized message) newest first and which asked
// for `limit` + 1 rows: at most `limit` parsed into `items`, and the token of the next page when
// the extra row came. Jobs and volumes page alike.
template <typename T, typename Parse>
absl::Status ReadPage(Stmt& q, int limit, Parse parse, const char* what, std::vector<T>* items,
                      std::string* next_page_token) {
  int64_t last_ord = 0;
  int rc;
  while ((rc = q.Step()) == SQLITE_ROW) {
    if (static_cast<int>(items->size()) == limit) {
      *next_page_token = EncodePageToken(last_ord);
      break;
    }
    last_ord = q.Int(0);
    auto item = parse(q.Text(1));
    if (!item.ok()) return item.status();
    items->push_back(std::move(*item));
  }
  if (rc != SQLITE_ROW && rc != SQLITE_DONE) return q.Error(what);
  return absl::OkStatus();
}

class SqliteJobStore : public JobStore {
 public:
  explicit SqliteJobStore(sqlite3* db) : db_(db) {}
  ~SqliteJobStore() override { sqlite3_close(db_); }

  absl::Status Init() {
    // auto_vacuum must precede the first table (it takes effect on a new file only): deleted
    // jobs then give their pages back through Compact() instead of keeping the file at its peak.
    const char* kSchema = R"sql(
      PRAGMA auto_vacuum=INCREMENTAL;
      PRAGMA journal_mode=WAL;
      PRAGMA synchronous=NORMAL;
      PRAGMA foreign_keys=ON;
      CREATE TABLE IF NOT EXISTS jobs(
        ord INTEGER PRIMARY KEY AUTOINCREMENT,
        id TEXT UNIQUE NOT NULL,
        request_id TEXT UNIQUE,
        state INTEGER NOT NULL,
        lease_owner TEXT,
        lease_expiry INTEGER NOT NULL DEFAULT 0,
        lease_epoch INTEGER NOT NULL DEFAULT 0,
        cancel_requested INTEGER NOT NULL DEFAULT 0,
        volume TEXT NOT NULL,
        job BLOB NOT NULL,
        creator TEXT NOT NULL DEFAULT '');
      CREATE INDEX IF NOT EXISTS jobs_by_state ON jobs(state, ord);
      CREATE TABLE IF NOT EXISTS events(
        job_id TEXT NOT NULL, seq INTEGER NOT NULL, event BLOB NOT NULL,
        PRIMARY KEY(job_id, seq)) WITHOUT ROWID;
      CREATE TABLE IF NOT EXISTS volumes(
        ord INTEGER PRIMARY KEY AUTOINCREMENT,
        id TEXT UNIQUE NOT NULL,
        request_id TEXT UNIQUE,
        volume BLOB NOT NULL,
        creator TEXT NOT NULL DEFAULT '',
        content_key TEXT);
      CREATE TABLE IF NOT EXISTS volume_blobs(
        volume_id TEXT NOT NULL, sha256 TEXT NOT NULL,
        PRIMARY KEY(volume_id, sha256)) WITHOUT ROWID;
      CREATE INDEX IF NOT EXISTS volume_blobs_by_sha ON volume_blobs(sha256);
      CREATE TABLE IF NOT EXISTS dicom_instances(
        ord INTEGER PRIMARY KEY AUTOINCREMENT,
        sop_instance_uid TEXT NOT NULL,
        series_instance_uid TEXT NOT NULL,
        sha256 TEXT NOT NULL,
        calling_ae TEXT NOT NULL, called_ae TEXT NOT NULL,
        received_ms INTEGER NOT NULL,
        aborted_ms INTEGER NOT NULL DEFAULT 0,
        size_bytes INTEGER NOT NULL DEFAULT 0,
        association_id TEXT NOT NULL DEFAULT '',
        UNIQUE(calling_ae, sop_instance_uid));
      CREATE TABLE IF NOT EXISTS dicom_series(
        ord INTEGER PRIMARY KEY AUTOINCREMENT,
        receive_key TEXT UNIQUE NOT NULL,
        instance_set TEXT NOT NULL,
        series_instance_uid TEXT NOT NULL,
        job TEXT NOT NULL, reason TEXT NOT NULL, route TEXT NOT NULL,
        results_pending INTEGER NOT NULL, send_status TEXT NOT NULL,
        update_ms INTEGER NOT NULL,
        state INTEGER NOT NULL DEFAULT 0,
        calling_ae TEXT NOT NULL DEFAULT '', called_ae TEXT NOT NULL DEFAULT '',
        instance_count INTEGER NOT NULL DEFAULT 0,
        first_received_ms INTEGER NOT NULL DEFAULT 0,
        last_received_ms INTEGER NOT NULL DEFAULT 0,
        association_id TEXT NOT NULL DEFAULT '');
    )sql";
    DECIMA_RETURN_IF_ERROR_LOCAL(Exec(kSchema));
    // Columns added since the first data dirs, each with the value its old rows get:
    // - jobs.lease_epoch: before leases had epochs (0 for every job);
    // - creator: before jobs and volumes had creators ("" for the old rows, which only an admin
    //   or reader sees; the proto carries the creator too, the column is the filter of a
    //   submitter's listing);
    // - volumes.content_key: before volumes were found by content (NULL for the old rows, which
    //   are then never reused: the next create of their content makes the row that later ones
    //   reuse);
    // - the receiver's: before the persisted abort mark and the ReceivedSeries fields (zero / ""
    //   for the old rows, whose state is then derived from job and reason, received_series.cc).
    const char* const kAddedColumns[][2] = {
        {"jobs", "lease_epoch INTEGER NOT NULL DEFAULT 0"},
        {"jobs", "creator TEXT NOT NULL DEFAULT ''"},
        {"volumes", "creator TEXT NOT NULL DEFAULT ''"},
        {"volumes", "content_key TEXT"},
        {"dicom_instances", "aborted_ms INTEGER NOT NULL DEFAULT 0"},
        {"dicom_series", "state INTEGER NOT NULL DEFAULT 0"},
        {"dicom_series", "calling_ae TEXT NOT NULL DEFAULT ''"},
        {"dicom_series", "called_ae TEXT NOT NULL DEFAULT ''"},
        {"dicom_series", "instance_count INTEGER NOT NULL DEFAULT 0"},
        {"dicom_series", "first_received_ms INTEGER NOT NULL DEFAULT 0"},
        {"dicom_series", "last_received_ms INTEGER NOT NULL DEFAULT 0"}};
    for (const auto& [table, decl] : kAddedColumns) {
      const std::string column(decl, std::string_view(decl).find(' '));
      Stmt c(db_, absl::StrCat("SELECT COUNT(*) FROM pragma_table_info('", table, "') WHERE name='",
                               column, "'")
                      .c_str());
      if (c.Step() != SQLITE_ROW) return c.Error("reading the schema");
      if (c.Int(0) == 0) {
        DECIMA_RETURN_IF_ERROR_LOCAL(
            Exec(absl::StrCat("ALTER TABLE ", table, " ADD COLUMN ", decl).c_str()));
      }
    }
    // One row per creator and content (NULLs are distinct), so old rows never collide.
    DECIMA_RETURN_IF_ERROR_LOCAL(Exec(
        "CREATE UNIQUE INDEX IF NOT EXISTS volumes_by_content ON volumes(creator, content_key)"));
    return absl::OkStatus();
  }

  // Data dirs whose receiver tables predate keying by sender and the per-receive history:
  // instances were unique by SOP Instance UID alone (another sender's instance replaced them)
  // and series rows by instance set (a re-send overwrote the earlier receive). SQLite cannot
  // change a UNIQUE constraint in place, so each table is rebuilt once, rows kept: an old
  // instance keeps its sender, size 0 (unknown, not counted against the quota); an old row's
  // receive key is its instance set (there was one row per set).
  absl::Status KeyDicomStateBySender() {
    auto has_column = [&](const char* table, const char* column) -> absl::StatusOr<bool> {
      Stmt c(db_, absl::StrCat("SELECT COUNT(*) FROM pragma_table_info('", table, "') WHERE name='",
                               column, "'")
                      .c_str());
      if (c.Step() != SQLITE_ROW) return c.Error("reading the schema");
      return c.Int(0) > 0;
    };
    auto rebuild = [&](const char* sql) {
      absl::Status st = Exec(sql);
      if (!st.ok()) (void)Exec("ROLLBACK");
      return st;
    };
    auto instances_keyed = has_column("dicom_instances", "size_bytes");
    if (!instances_keyed.ok()) return instances_keyed.status();
    if (!*instances_keyed) {
      DECIMA_RETURN_IF_ERROR_LOCAL(rebuild(R"sql(
        BEGIN IMMEDIATE;
        DROP INDEX IF EXISTS dicom_instances_by_sha;
        ALTER TABLE dicom_instances RENAME TO dicom_instances_unkeyed;
        CREATE TABLE dicom_instances(
          ord INTEGER PRIMARY KEY AUTOINCREMENT,
          sop_instance_uid TEXT NOT NULL,
          series_instance_uid TEXT NOT NULL,
          sha256 TEXT NOT NULL,
          calling_ae TEXT NOT NULL, called_ae TEXT NOT NULL,
          received_ms INTEGER NOT NULL,
          aborted_ms INTEGER NOT NULL DEFAULT 0,
          size_bytes INTEGER NOT NULL DEFAULT 0,
          UNIQUE(calling_ae, sop_instance_uid));
        INSERT INTO dicom_instances(sop_instance_uid, series_instance_uid, sha256, calling_ae,
                                    called_ae, received_ms, aborted_ms)
          SELECT sop_instance_uid, series_instance_uid, sha256, calling_ae, called_ae,
                 received_ms, aborted_ms FROM dicom_instances_unkeyed ORDER BY ord;
        DROP TABLE dicom_instances_unkeyed;
        COMMIT;
      )sql"));
    }
    auto series_keyed = has_column("dicom_series", "receive_key");
    if (!series_keyed.ok()) return series_keyed.status();
    if (!*series_keyed) {
      DECIMA_RETURN_IF_ERROR_LOCAL(rebuild(R"sql(
        BEGIN IMMEDIATE;
        ALTER TABLE dicom_series RENAME TO dicom_series_by_set;
        CREATE TABLE dicom_series(
          ord INTEGER PRIMARY KEY AUTOINCREMENT,
          receive_key TEXT UNIQUE NOT NULL,
          instance_set TEXT NOT NULL,
          series_instance_uid TEXT NOT NULL,
          job TEXT NOT NULL, reason TEXT NOT NULL, route TEXT NOT NULL,
          results_pending INTEGER NOT NULL, send_status TEXT NOT NULL,
          update_ms INTEGER NOT NULL,
          state INTEGER NOT NULL DEFAULT 0,
          calling_ae TEXT NOT NULL DEFAULT '', called_ae TEXT NOT NULL DEFAULT '',
          instance_count INTEGER NOT NULL DEFAULT 0,
          first_received_ms INTEGER NOT NULL DEFAULT 0,
          last_received_ms INTEGER NOT NULL DEFAULT 0);
        INSERT INTO dicom_series(receive_key, instance_set, series_instance_uid, job, reason, route,
                                 results_pending, send_status, update_ms, state, calling_ae,
                                 called_ae, instance_count, first_received_ms, last_received_ms)
          SELECT instance_set, instance_set, series_instance_uid, job, reason, route,
                 results_pending, send_status, update_ms, state, calling_ae, called_ae,
                 instance_count, first_received_ms, last_received_ms
          FROM dicom_series_by_set ORDER BY ord;
        DROP TABLE dicom_series_by_set;
        COMMIT;
      )sql"));
    }
    DECIMA_RETURN_IF_ERROR_LOCAL(
        Exec("CREATE INDEX IF NOT EXISTS dicom_instances_by_sha ON dicom_instances(sha256);"
             "CREATE INDEX IF NOT EXISTS dicom_instances_by_sender "
             "ON dicom_instances(calling_ae, series_instance_uid)"));
    // Data dirs whose receiver tables predate association ids: the column, "" for the old
    // rows. Added after the rebuilds above, which copy the columns of their time only.
    for (const char* table : {"dicom_instances", "dicom_series"}) {
      auto has = has_column(table, "association_id");
      if (!has.ok()) return has.status();
      if (!*has) {
        DECIMA_RETURN_IF_ERROR_LOCAL(
            Exec(absl::StrCat("ALTER TABLE ", table,
                              " ADD COLUMN association_id TEXT NOT NULL DEFAULT ''")
                     .c_str()));
      }
    }
    return absl::OkStatus();
  }

  bool exclusive() const override { return true; }

  void SetListener(EventListener listener) override {
    std::lock_guard<std::mutex> lock(mu_);
    listener_ = std::move(listener);
  }

  absl::StatusOr<v1::Job> CreateJob(const std::string& id, const v1::JobSpec& spec,
                                    const std::string& request_id, int max_queued,
                                    const std::string& creator, bool* created) override {
    std::lock_guard<std::mutex> lock(mu_);
    *created = false;
    if (!request_id.empty()) {
      Stmt q(db_, "SELECT job FROM jobs WHERE request_id=?");
      q.Bind(1, request_id);
      if (q.Step() == SQLITE_ROW) return ParseJob(q.Text(0));
    }
    Tx tx(this);
    if (!tx.ok()) return tx.status();
    {
      Stmt c(db_, "SELECT COUNT(*) FROM jobs WHERE state=?");
      c.Bind(1, int64_t{v1::QUEUED});
      if (c.Step() != SQLITE_ROW) return c.Error("counting queued jobs");
      DECIMA_RETURN_IF_ERROR_LOCAL(CheckQueueRoom(c.Int(0), max_queued));
    }
    v1::Job job = NewQueuedJob(id, spec, request_id, creator, &pending_);
    Stmt ins(db_,
             "INSERT INTO jobs(id, request_id, state, volume, job, creator) VALUES(?,?,?,?,?,?)");
    ins.Bind(1, id);
    if (request_id.empty()) {
      ins.BindNull(2);
    } else {
      ins.Bind(2, request_id);
    }
    ins.Bind(3, int64_t{job.state()}).Bind(4, spec.volume()).BindBlob(5, job.SerializeAsString());
    ins.Bind(6, creator);
    if (ins.Step() != SQLITE_DONE) return ins.Error("inserting job");
    DECIMA_RETURN_IF_ERROR_LOCAL(SaveEvents());
    DECIMA_TX_COMMIT(tx);
    *created = true;
    return job;
  }

  absl::StatusOr<v1::Job> GetJob(const std::string& id) override {
    std::lock_guard<std::mutex> lock(mu_);
    return LoadJob(id);
  }

  absl::StatusOr<JobPage> ListJobs(const std::vector<v1::JobState>& states,
                                   const std::string& creator, int page_size,
                                   const std::string& page_token) override {
    auto before = DecodePageToken(page_token);
    if (!before.ok()) return before.status();
    int limit = ClampPageSize(page_size);
    std::string sql = "SELECT ord, job FROM jobs WHERE ord < ?";
    if (!states.empty()) {
      std::vector<std::string> parts;
      for (auto s : states) parts.push_back(absl::StrCat(static_cast<int>(s)));
      absl::StrAppend(&sql, " AND state IN (", absl::StrJoin(parts, ","), ")");
    }
    if (!creator.empty()) absl::StrAppend(&sql, " AND creator = ?");
    absl::StrAppend(&sql, " ORDER BY ord DESC LIMIT ?");
    std::lock_guard<std::mutex> lock(mu_);
    Stmt q(db_, sql.c_str());
    int arg = 1;
    q.Bind(arg++, *before);
    if (!creator.empty()) q.Bind(arg++, creator);
    q.Bind(arg, int64_t{limit} + 1);
    JobPage page;
    DECIMA_RETURN_IF_ERROR_LOCAL(ReadPage(
        q, limit, [](const std::string& row) { return ParseJob(row); }, "listing jobs", &page.jobs,
        &page.next_page_token));
    return page;
  }

  absl::StatusOr<int64_t> CountJobs(v1::JobState state) override {
    std::lock_guard<std::mutex> lock(mu_);
    Stmt c(db_, "SELECT COUNT(*) FROM jobs WHERE state=?");
    c.Bind(1, int64_t{state});
    if (c.Step() != SQLITE_ROW) return c.Error("counting jobs");
    return c.Int(0);
  }

  absl::StatusOr<std::optional<Claim>> ClaimNext(const std::string& owner,
                                                 int64_t lease_ms) override {
    std::lock_guard<std::mutex> lock(mu_);
    Tx tx(this);
    if (!tx.ok()) return tx.status();
    Stmt q(db_, "SELECT job, lease_epoch FROM jobs WHERE state=? ORDER BY ord LIMIT 1");
    q.Bind(1, int64_t{v1::QUEUED});
    int rc = q.Step();
    if (rc == SQLITE_DONE) return std::optional<Claim>();
    if (rc != SQLITE_ROW) return q.Error("claiming a job");
    auto job = ParseJob(q.Text(0));
    if (!job.ok()) return job.status();
    Claim claim;
    claim.lease = {job->name().substr(5), owner, q.Int(1) + 1};
    StartAttempt(*job, &pending_);
    DECIMA_RETURN_IF_ERROR_LOCAL(SaveJob(*job, owner, NowMs() + lease_ms, /*cancel=*/0));
    Stmt e(db_, "UPDATE jobs SET lease_epoch=? WHERE id=?");
    e.Bind(1, claim.lease.epoch).Bind(2, claim.lease.job_id);
    if (e.Step() != SQLITE_DONE) return e.Error("claiming a job");
    DECIMA_TX_COMMIT(tx);
    claim.job = std::move(*job);
    return std::optional<Claim>(std::move(claim));
  }

  absl::Status RenewLease(const Lease& lease, int64_t lease_ms) override {
    std::lock_guard<std::mutex> lock(mu_);
    Stmt u(db_,
           "UPDATE jobs SET lease_expiry=? WHERE id=? AND state=? AND lease_owner=? AND "
           "lease_epoch=?");
    u.Bind(1, NowMs() + lease_ms).Bind(2, lease.job_id).Bind(3, int64_t{v1::RUNNING});
    u.Bind(4, lease.owner).Bind(5, lease.epoch);
    if (u.Step() != SQLITE_DONE) return u.Error("renewing a lease");
    if (sqlite3_changes(db_) != 1) {
      return absl::FailedPreconditionError(absl::StrCat(
          "jobs/", lease.job_id, " is no longer leased to ", lease.owner, " epoch ", lease.epoch));
    }
    return absl::OkStatus();
  }

  absl::Status AppendProgress(const Lease& lease, const v1::Progress& progress) override {
    std::lock_guard<std::mutex> lock(mu_);
    Tx tx(this);
    if (!tx.ok()) return tx.status();
    auto job = LoadHeld(lease);
    if (!job.ok()) return job.status();
    RecordProgress(*job, progress, &pending_);
    DECIMA_RETURN_IF_ERROR_LOCAL(SaveJobKeepLease(*job));
    DECIMA_TX_COMMIT(tx);
    return absl::OkStatus();
  }

  absl::StatusOr<v1::Job> Finish(const Lease& lease, v1::JobState state,
                                 const v1::Job& outcome) override {
    std::lock_guard<std::mutex> lock(mu_);
    Tx tx(this);
    if (!tx.ok()) return tx.status();
    auto job = LoadHeld(lease);
    if (!job.ok()) return job.status();
    FinishAttempt(*job, state, outcome, &pending_);
    DECIMA_RETURN_IF_ERROR_LOCAL(SaveJob(*job, "", 0, 0));
    DECIMA_TX_COMMIT(tx);
    return *job;
  }

  absl::StatusOr<v1::Job> Requeue(const Lease& lease, const std::string& reason) override {
    std::lock_guard<std::mutex> lock(mu_);
    Tx tx(this);
    if (!tx.ok()) return tx.status();
    auto job = LoadHeld(lease);
    if (!job.ok()) return job.status();
    RequeueAttempt(*job, reason, &pending_);
    DECIMA_RETURN_IF_ERROR_LOCAL(SaveJob(*job, "", 0, 0));
    DECIMA_TX_COMMIT(tx);
    return *job;
  }

  absl::StatusOr<Recovered> RecoverLeases(bool all, int max_attempts) override {
    std::lock_guard<std::mutex> lock(mu_);
    Tx tx(this);
    if (!tx.ok()) return tx.status();
    Stmt q(db_, all ? "SELECT job, cancel_requested FROM jobs WHERE state=?"
                    : "SELECT job, cancel_requested FROM jobs WHERE state=? AND lease_expiry<?");
    q.Bind(1, int64_t{v1::RUNNING});
    if (!all) q.Bind(2, NowMs());
    std::vector<std::pair<v1::Job, bool>> lapsed;
    int rc;
    while ((rc = q.Step()) == SQLITE_ROW) {
      auto job = ParseJob(q.Text(0));
      if (!job.ok()) return job.status();
      lapsed.emplace_back(std::move(*job), q.Int(1) != 0);
    }
    if (rc != SQLITE_DONE) return q.Error("finding lapsed leases");
    Recovered out;
    for (auto& [job, cancel] : lapsed) {
      const bool requeued =
          ResolveLapsedLease(job, cancel, max_attempts, &pending_) == LapsedLease::kRequeued;
      (requeued ? out.requeued : out.failed).push_back(JobIdOf(job));
      DECIMA_RETURN_IF_ERROR_LOCAL(SaveJob(job, "", 0, 0));
    }
    DECIMA_TX_COMMIT(tx);
    return out;
  }

  absl::StatusOr<v1::Job> Cancel(const std::string& id) override {
    std::lock_guard<std::mutex> lock(mu_);
    Tx tx(this);
    if (!tx.ok()) return tx.status();
    auto job = LoadJob(id);
    if (!job.ok()) return job.status();
    if (job->state() == v1::QUEUED) {
      CancelQueued(*job, &pending_);
      DECIMA_RETURN_IF_ERROR_LOCAL(SaveJob(*job, "", 0, 0));
    } else if (job->state() == v1::RUNNING) {
      Stmt u(db_, "UPDATE jobs SET cancel_requested=1 WHERE id=?");
      u.Bind(1, id);
      if (u.Step() != SQLITE_DONE) return u.Error("requesting cancel");
    }
    DECIMA_TX_COMMIT(tx);
    return *job;
  }

  absl::StatusOr<bool> CancelRequested(const std::string& id) override {
    std::lock_guard<std::mutex> lock(mu_);
    Stmt q(db_, "SELECT cancel_requested FROM jobs WHERE id=?");
    q.Bind(1, id);
    if (q.Step() != SQLITE_ROW) return absl::NotFoundError(absl::StrCat("job ", id, " not found"));
    return q.Int(0) != 0;
  }

  absl::StatusOr<v1::Job> Retry(const std::string& id, int max_queued) override {
    std::lock_guard<std::mutex> lock(mu_);
    Tx tx(this);
    if (!tx.ok()) return tx.status();
    auto job = LoadJob(id);
    if (!job.ok()) return job.status();
    DECIMA_RETURN_IF_ERROR_LOCAL(CheckRetryable(*job));
    Stmt c(db_, "SELECT COUNT(*) FROM jobs WHERE state=?");
    c.Bind(1, int64_t{v1::QUEUED});
    if (c.Step() != SQLITE_ROW) return c.Error("counting queued jobs");
    DECIMA_RETURN_IF_ERROR_LOCAL(CheckQueueRoom(c.Int(0), max_queued));
    ResetForRetry(*job, &pending_);
    DECIMA_RETURN_IF_ERROR_LOCAL(SaveJob(*job, "", 0, 0));
    DECIMA_TX_COMMIT(tx);
    return *job;
  }

  absl::Status DeleteJob(const std::string& id) override {
    std::lock_guard<std::mutex> lock(mu_);
    Tx tx(this);
    if (!tx.ok()) return tx.status();
    auto job = LoadJob(id);
    if (!job.ok()) return job.status();
    DECIMA_RETURN_IF_ERROR_LOCAL(CheckDeletable(*job));
    Stmt d1(db_, "DELETE FROM events WHERE job_id=?");
    d1.Bind(1, id);
    if (d1.Step() != SQLITE_DONE) return d1.Error("deleting events");
    Stmt d2(db_, "DELETE FROM jobs WHERE id=?");
    d2.Bind(1, id);
    if (d2.Step() != SQLITE_DONE) return d2.Error("deleting job");
    DECIMA_TX_COMMIT(tx);
    return absl::OkStatus();
  }

  absl::StatusOr<std::vector<v1::JobEvent>> ListEvents(const std::string& id, int64_t after,
                                                       int limit) override {
    std::lock_guard<std::mutex> lock(mu_);
    Stmt q(db_, "SELECT event FROM events WHERE job_id=? AND seq>? ORDER BY seq LIMIT ?");
    q.Bind(1, id).Bind(2, after).Bind(3, int64_t{limit});
    std::vector<v1::JobEvent> out;
    int rc;
    while ((rc = q.Step()) == SQLITE_ROW) {
      v1::JobEvent ev;
      if (!ev.ParseFromString(q.Text(0))) return absl::DataLossError("job store: bad event row");
      out.push_back(std::move(ev));
    }
    if (rc != SQLITE_DONE) return q.Error("listing events");
    return out;
  }

  absl::StatusOr<v1::Volume> CreateVolume(const std::string& id, const v1::Volume& volume,
                                          const std::string& request_id,
                                          const std::string& content_key, bool* created) override {
    std::lock_guard<std::mutex> lock(mu_);
    *created = false;
    if (!request_id.empty()) {
      Stmt q(db_, "SELECT volume FROM volumes WHERE request_id=?");
      q.Bind(1, request_id);
      if (q.Step() == SQLITE_ROW) return ParseVolume(q.Text(0));
    }
    if (!content_key.empty()) {
      Stmt q(db_, "SELECT volume FROM volumes WHERE creator=? AND content_key=?");
      q.Bind(1, volume.creator()).Bind(2, content_key);
      if (q.Step() == SQLITE_ROW) return ParseVolume(q.Text(0));
    }
    Tx tx(this);
    if (!tx.ok()) return tx.status();
    Stmt ins(db_,
             "INSERT INTO volumes(id, request_id, volume, creator, content_key) VALUES(?,?,?,?,?)");
    ins.Bind(1, id);
    if (request_id.empty()) {
      ins.BindNull(2);
    } else {
      ins.Bind(2, request_id);
    }
    ins.BindBlob(3, volume.SerializeAsString());
    ins.Bind(4, volume.creator());
    if (content_key.empty()) {
      ins.BindNull(5);
    } else {
      ins.Bind(5, content_key);
    }
    if (ins.Step() != SQLITE_DONE) return ins.Error("inserting volume");
    for (const auto& f : volume.files()) {
      // The catalog checked the names; a store never trusts its caller with substr.
      if (!absl::StartsWith(f.blob(), "blobs/")) {
        return absl::InvalidArgumentError(absl::StrCat("job store: volume file ", f.path(),
                                                       ": blob '", f.blob(),
                                                       "' is not 'blobs/{sha256}'"));
      }
      Stmt b(db_, "INSERT OR IGNORE INTO volume_blobs(volume_id, sha256) VALUES(?,?)");
      b.Bind(1, id).Bind(2, f.blob().substr(6));
      if (b.Step() != SQLITE_DONE) return b.Error("inserting volume blob");
    }
    DECIMA_TX_COMMIT(tx);
    *created = true;
    return volume;
  }

  absl::StatusOr<v1::Volume> GetVolume(const std::string& id) override {
    std::lock_guard<std::mutex> lock(mu_);
    Stmt q(db_, "SELECT volume FROM volumes WHERE id=?");
    q.Bind(1, id);
    int rc = q.Step();
    if (rc == SQLITE_DONE) return absl::NotFoundError(absl::StrCat("volumes/", id, " not found"));
    if (rc != SQLITE_ROW) return q.Error("reading volume");
    return ParseVolume(q.Text(0));
  }

  absl::StatusOr<VolumePage> ListVolumes(const std::string& creator, int page_size,
                                         const std::string& page_token) override {
    auto before = DecodePageToken(page_token);
    if (!before.ok()) return before.status();
    int limit = ClampPageSize(page_size);
    std::lock_guard<std::mutex> lock(mu_);
    Stmt q(db_, creator.empty()
                    ? "SELECT ord, volume FROM volumes WHERE ord < ? ORDER BY ord DESC LIMIT ?"
                    : "SELECT ord, volume FROM volumes WHERE ord < ? AND creator = ? "
                      "ORDER BY ord DESC LIMIT ?");
    int arg = 1;
    q.Bind(arg++, *before);
    if (!creator.empty()) q.Bind(arg++, creator);
    q.Bind(arg, int64_t{limit} + 1);
    VolumePage page;
    DECIMA_RETURN_IF_ERROR_LOCAL(ReadPage(
        q, limit, [](const std::string& row) { return ParseVolume(row); }, "listing volumes",
        &page.volumes, &page.next_page_token));
    return page;
  }

  absl::Status DeleteVolume(const std::string& id) override {
    std::lock_guard<std::mutex> lock(mu_);
    Tx tx(this);
    if (!tx.ok()) return tx.status();
    Stmt q(db_, "SELECT COUNT(*) FROM volumes WHERE id=?");
    q.Bind(1, id);
    if (q.Step() != SQLITE_ROW || q.Int(0) == 0) {
      return absl::NotFoundError(absl::StrCat("volumes/", id, " not found"));
    }
    // A queued or running job reads the volume as its input or its label map (the label map
    // lives only in the stored spec, so the active jobs' specs are read: at most max_queued).
    const std::string name = absl::StrCat("volumes/", id);
    Stmt u(db_, "SELECT job FROM jobs WHERE state IN (?,?)");
    u.Bind(1, int64_t{v1::QUEUED}).Bind(2, int64_t{v1::RUNNING});
    int64_t readers = 0;
    for (int rc; (rc = u.Step()) != SQLITE_DONE;) {
      if (rc != SQLITE_ROW) return u.Error("checking volume use");
      auto job = ParseJob(u.Text(0));
      if (!job.ok()) return job.status();
      if (job->spec().volume() == name || job->spec().label_map() == name) ++readers;
    }
    if (readers > 0) {
      return absl::FailedPreconditionError(absl::StrCat(
          name, " is read by ", readers, " queued or running job(s) (as volume or label map)"));
    }
    Stmt d(db_, "DELETE FROM volumes WHERE id=?");
    d.Bind(1, id);
    if (d.Step() != SQLITE_DONE) return d.Error("deleting volume");
    Stmt d2(db_, "DELETE FROM volume_blobs WHERE volume_id=?");
    d2.Bind(1, id);
    if (d2.Step() != SQLITE_DONE) return d2.Error("deleting volume blobs");
    DECIMA_TX_COMMIT(tx);
    return absl::OkStatus();
  }

  absl::Status Compact() override {
    std::lock_guard<std::mutex> lock(mu_);
    return Exec("PRAGMA incremental_vacuum");
  }

  absl::StatusOr<bool> BlobInUse(const std::string& sha256) override {
    std::lock_guard<std::mutex> lock(mu_);
    Stmt q(db_,
           "SELECT (SELECT COUNT(*) FROM volume_blobs WHERE sha256=?1) + "
           "(SELECT COUNT(*) FROM dicom_instances WHERE sha256=?1)");
    q.Bind(1, sha256);
    if (q.Step() != SQLITE_ROW) return q.Error("checking blob use");
    return q.Int(0) > 0;
  }

  absl::Status PutDicomInstance(const DicomInstanceRecord& r) override {
    std::lock_guard<std::mutex> lock(mu_);
    Tx tx(this);
    if (!tx.ok()) return tx.status();
    {
      Stmt held(db_,
                "SELECT sha256 FROM dicom_instances WHERE calling_ae=? AND sop_instance_uid=?");
      held.Bind(1, r.calling_ae).Bind(2, r.sop_instance_uid);
      const int rc = held.Step();
      if (rc == SQLITE_ROW && held.Text(0) != r.sha256) {
        return absl::AlreadyExistsError(absl::StrCat(
            "SOP instance ", r.sop_instance_uid, " from ", r.calling_ae,
            " is already held with other bytes (sha256 ", held.Text(0), ", now ", r.sha256, ")"));
      }
      if (rc != SQLITE_ROW && rc != SQLITE_DONE) return held.Error("reading a DICOM instance");
    }
    // REPLACE gives a re-sent instance a new ord: the series order stays "as last received".
    Stmt q(db_,
           "INSERT OR REPLACE INTO dicom_instances(sop_instance_uid, series_instance_uid, sha256, "
           "calling_ae, called_ae, received_ms, aborted_ms, size_bytes, association_id) "
           "VALUES(?,?,?,?,?,?,?,?,?)");
    q.Bind(1, r.sop_instance_uid).Bind(2, r.series_instance_uid).Bind(3, r.sha256);
    q.Bind(4, r.calling_ae).Bind(5, r.called_ae).Bind(6, r.received_ms).Bind(7, r.aborted_ms);
    q.Bind(8, r.size_bytes).Bind(9, r.association_id);
    if (q.Step() != SQLITE_DONE) return q.Error("storing a DICOM instance");
    DECIMA_TX_COMMIT(tx);
    return absl::OkStatus();
  }

  absl::StatusOr<std::vector<DicomInstanceRecord>> ListDicomInstances() override {
    std::lock_guard<std::mutex> lock(mu_);
    return SelectDicomInstances("", "", "");
  }

  absl::Status MarkDicomSeriesAborted(const std::string& calling_ae,
                                      const std::string& series_instance_uid,
                                      int64_t aborted_ms) override {
    std::lock_guard<std::mutex> lock(mu_);
    Stmt q(db_,
           "UPDATE dicom_instances SET aborted_ms=? WHERE calling_ae=? AND series_instance_uid=?");
    q.Bind(1, aborted_ms).Bind(2, calling_ae).Bind(3, series_instance_uid);
    if (q.Step() != SQLITE_DONE) return q.Error("marking a DICOM series aborted");
    return absl::OkStatus();
  }

  absl::Status PutDicomSeries(const DicomSeriesRecord& r,
                              const std::vector<std::string>& consumed) override {
    std::lock_guard<std::mutex> lock(mu_);
    Tx tx(this);
    if (!tx.ok()) return tx.status();
    Stmt q(db_,
           "INSERT INTO dicom_series(receive_key, instance_set, series_instance_uid, job, reason, "
           "route, results_pending, send_status, update_ms, state, calling_ae, called_ae, "
           "instance_count, first_received_ms, last_received_ms, association_id) "
           "VALUES(?15,?1,?2,?3,?4,?5,?6,?7,?8,?9,?10,?11,?12,?13,?14,?16) "
           "ON CONFLICT(receive_key) DO UPDATE SET instance_set=?1, job=?3, reason=?4, route=?5, "
           "results_pending=?6, send_status=?7, update_ms=?8, state=?9, calling_ae=?10, "
           "called_ae=?11, instance_count=?12, first_received_ms=?13, last_received_ms=?14, "
           "association_id=?16");
    q.Bind(1, r.instance_set).Bind(2, r.series_instance_uid).Bind(3, r.job).Bind(4, r.reason);
    q.Bind(5, r.route).Bind(6, int64_t{r.results_pending ? 1 : 0}).Bind(7, r.send_status);
    q.Bind(8, r.update_ms).Bind(9, int64_t{r.state}).Bind(10, r.calling_ae);
    q.Bind(11, r.called_ae).Bind(12, int64_t{r.instance_count}).Bind(13, r.first_received_ms);
    q.Bind(14, r.last_received_ms).Bind(15, r.receive_key).Bind(16, r.association_id);
    if (q.Step() != SQLITE_DONE) return q.Error("storing a DICOM series outcome");
    for (const auto& uid : consumed) {
      Stmt d(db_, "DELETE FROM dicom_instances WHERE calling_ae=? AND sop_instance_uid=?");
      d.Bind(1, r.calling_ae).Bind(2, uid);
      if (d.Step() != SQLITE_DONE) return d.Error("removing consumed DICOM instances");
    }
    DECIMA_TX_COMMIT(tx);
    return absl::OkStatus();
  }

  absl::StatusOr<std::vector<DicomSeriesRecord>> ListDicomSeries(bool pending_only,
                                                                 int limit) override {
    std::lock_guard<std::mutex> lock(mu_);
    Stmt q(db_,
           absl::StrCat("SELECT instance_set, series_instance_uid, job, reason, route, "
                        "results_pending, send_status, update_ms, state, calling_ae, "
                        "called_ae, instance_count, first_received_ms, last_received_ms, "
                        "receive_key, association_id FROM dicom_series ",
                        pending_only ? "WHERE results_pending=1 " : "", "ORDER BY ord DESC LIMIT ?")
               .c_str());
    q.Bind(1, int64_t{limit});
    std::vector<DicomSeriesRecord> out;
    int rc;
    while ((rc = q.Step()) == SQLITE_ROW) {
      DicomSeriesRecord r;
      r.instance_set = q.Text(0);
      r.series_instance_uid = q.Text(1);
      r.job = q.Text(2);
      r.reason = q.Text(3);
      r.route = q.Text(4);
      r.results_pending = q.Int(5) != 0;
      r.send_status = q.Text(6);
      r.update_ms = q.Int(7);
      r.state = static_cast<v1::ReceivedSeries::State>(q.Int(8));
      r.calling_ae = q.Text(9);
      r.called_ae = q.Text(10);
      r.instance_count = static_cast<int>(q.Int(11));
      r.first_received_ms = q.Int(12);
      r.last_received_ms = q.Int(13);
      r.receive_key = q.Text(14);
      r.association_id = q.Text(15);
      out.push_back(std::move(r));
    }
    if (rc != SQLITE_DONE) return q.Error("listing DICOM series");
    return out;
  }

  absl::StatusOr<std::vector<DicomInstanceRecord>> RemoveDicomInstances(
      const std::string& calling_ae, const std::string& series_instance_uid) override {
    std::lock_guard<std::mutex> lock(mu_);
    Tx tx(this);
    if (!tx.ok()) return tx.status();
    auto removed = SelectDicomInstances("WHERE calling_ae=?1 AND series_instance_uid=?2 ",
                                        calling_ae, series_instance_uid);
    if (!removed.ok()) return removed.status();
    Stmt d(db_, "DELETE FROM dicom_instances WHERE calling_ae=? AND series_instance_uid=?");
    d.Bind(1, calling_ae).Bind(2, series_instance_uid);
    if (d.Step() != SQLITE_DONE) return d.Error("removing DICOM instances");
    DECIMA_TX_COMMIT(tx);
    return removed;
  }

  absl::StatusOr<int64_t> DicomWaitingBytes(const std::string& calling_ae) override {
    std::lock_guard<std::mutex> lock(mu_);
    Stmt q(db_, "SELECT COALESCE(SUM(size_bytes), 0) FROM dicom_instances WHERE calling_ae=?");
    q.Bind(1, calling_ae);
    if (q.Step() != SQLITE_ROW) return q.Error("summing a sender's DICOM instances");
    return q.Int(0);
  }

 private:
  // The received instances matching `where` (binding ?1 and ?2 when not empty), arrival order.
  absl::StatusOr<std::vector<DicomInstanceRecord>> SelectDicomInstances(const std::string& where,
                                                                        const std::string& a,
                                                                        const std::string& b) {
    Stmt q(db_, absl::StrCat("SELECT series_instance_uid, sop_instance_uid, sha256, calling_ae, "
                             "called_ae, received_ms, aborted_ms, size_bytes, association_id "
                             "FROM dicom_instances ",
                             where, "ORDER BY ord")
                    .c_str());
    if (!where.empty()) q.Bind(1, a).Bind(2, b);
    std::vector<DicomInstanceRecord> out;
    int rc;
    while ((rc = q.Step()) == SQLITE_ROW) {
      out.push_back({q.Text(0), q.Text(1), q.Text(2), q.Text(3), q.Text(4), q.Int(5), q.Int(6),
                     q.Int(7), q.Text(8)});
    }
    if (rc != SQLITE_DONE) return q.Error("listing DICOM instances");
    return out;
  }

  // BEGIN IMMEDIATE on construction, ROLLBACK on destruction unless committed. Events added
  // during the transaction are handed to the listener after COMMIT.
  class Tx {
   public:
    explicit Tx(SqliteJobStore* s) : s_(s) {
      status_ = s_->Exec("BEGIN IMMEDIATE");
      s_->pending_.clear();
      s_->saved_ = 0;
    }
    ~Tx() {
      if (status_.ok() && !done_) {
        (void)s_->Exec("ROLLBACK");
        s_->pending_.clear();
        s_->saved_ = 0;
      }
    }
    bool ok() const { return status_.ok(); }
    absl::Status status() const { return status_; }
    absl::Status Commit() {
      absl::Status st = s_->Exec("COMMIT");
      if (!st.ok()) return st;
      done_ = true;
      if (s_->listener_) {
        for (auto& [id, ev] : s_->pending_) s_->listener_(id, ev);
      }
      s_->pending_.clear();
      return absl::OkStatus();
    }

   private:
    SqliteJobStore* s_;
    absl::Status status_;
    bool done_ = false;
  };

  absl::Status Exec(const char* sql) {
    char* err = nullptr;
    if (sqlite3_exec(db_, sql, nullptr, nullptr, &err) != SQLITE_OK) {
      std::string msg = err ? err : "unknown error";
      sqlite3_free(err);
      return absl::InternalError(absl::StrCat("job store: ", msg));
    }
    return absl::OkStatus();
  }

  static absl::StatusOr<v1::Job> ParseJob(const std::string& bytes) {
    v1::Job job;
    if (!job.ParseFromString(bytes)) return absl::DataLossError("job store: bad job row");
    return job;
  }
  static absl::StatusOr<v1::Volume> ParseVolume(const std::string& bytes) {
    v1::Volume v;
    if (!v.ParseFromString(bytes)) return absl::DataLossError("job store: bad volume row");
    return v;
  }

  absl::StatusOr<v1::Job> LoadJob(const std::string& id) {
    Stmt q(db_, "SELECT job FROM jobs WHERE id=?");
    q.Bind(1, id);
    int rc = q.Step();
    if (rc == SQLITE_DONE) return absl::NotFoundError(absl::StrCat("jobs/", id, " not found"));
    if (rc != SQLITE_ROW) return q.Error("reading job");
    return ParseJob(q.Text(0));
  }

  // The job, if RUNNING under exactly `lease` (owner and epoch).
  absl::StatusOr<v1::Job> LoadHeld(const Lease& lease) {
    Stmt q(db_, "SELECT job, state, lease_owner, lease_epoch FROM jobs WHERE id=?");
    q.Bind(1, lease.job_id);
    int rc = q.Step();
    if (rc == SQLITE_DONE) {
      return absl::NotFoundError(absl::StrCat("jobs/", lease.job_id, " not found"));
    }
    if (rc != SQLITE_ROW) return q.Error("reading job");
    if (q.Int(1) != v1::RUNNING || q.Text(2) != lease.owner || q.Int(3) != lease.epoch) {
      return absl::FailedPreconditionError(absl::StrCat("jobs/", lease.job_id,
                                                        " is not running under lease ", lease.owner,
                                                        " epoch ", lease.epoch));
    }
    return ParseJob(q.Text(0));
  }

  // Writes the job row and the events added since the transaction began.
  absl::Status SaveJob(const v1::Job& job, const std::string& owner, int64_t expiry, int cancel) {
    Stmt u(db_,
           "UPDATE jobs SET state=?, lease_owner=?, lease_expiry=?, cancel_requested=?, job=? "
           "WHERE id=?");
    u.Bind(1, int64_t{job.state()});
    if (owner.empty()) {
      u.BindNull(2);
    } else {
      u.Bind(2, owner);
    }
    u.Bind(3, expiry).Bind(4, int64_t{cancel}).BindBlob(5, job.SerializeAsString());
    u.Bind(6, job.name().substr(5));
    if (u.Step() != SQLITE_DONE) return u.Error("updating job");
    return SaveEvents();
  }

  absl::Status SaveJobKeepLease(const v1::Job& job) {
    Stmt u(db_, "UPDATE jobs SET job=? WHERE id=?");
    u.BindBlob(1, job.SerializeAsString()).Bind(2, job.name().substr(5));
    if (u.Step() != SQLITE_DONE) return u.Error("updating job");
    return SaveEvents();
  }

  absl::Status SaveEvents() {
    for (size_t i = saved_; i < pending_.size(); ++i) {
      Stmt ins(db_, "INSERT INTO events(job_id, seq, event) VALUES(?,?,?)");
      ins.Bind(1, pending_[i].first)
          .Bind(2, pending_[i].second.sequence())
          .BindBlob(3, pending_[i].second.SerializeAsString());
      if (ins.Step() != SQLITE_DONE) return ins.Error("inserting event");
    }
    saved_ = pending_.size();
    return absl::OkStatus();
  }

  sqlite3* db_;
  std::mutex mu_;  // guards the connection and everything below
  EventListener listener_;
  PendingEvents pending_;  // appended by the lifecycle rules, written by SaveEvents
  size_t saved_ = 0;
};

}  // namespace

google::protobuf::Timestamp NowTimestamp() {
  auto ns = std::chrono::duration_cast<std::chrono::nanoseconds>(
                std::chrono::system_clock::now().time_since_epoch())
                .count();
  google::protobuf::Timestamp t;
  t.set_seconds(ns / 1000000000);
  t.set_nanos(static_cast<int32_t>(ns % 1000000000));
  return t;
}

bool IsFinal(v1::JobState state) {
  return state == v1::SUCCEEDED || state == v1::FAILED || state == v1::CANCELLED;
}

absl::StatusOr<std::unique_ptr<JobStore>> OpenSqliteJobStore(const std::string& path) {
  sqlite3* db = nullptr;
  int rc = sqlite3_open_v2(
      path.c_str(), &db, SQLITE_OPEN_READWRITE | SQLITE_OPEN_CREATE | SQLITE_OPEN_NOMUTEX, nullptr);
  if (rc != SQLITE_OK) {
    std::string msg = db ? sqlite3_errmsg(db) : "out of memory";
    sqlite3_close(db);
    return absl::InternalError(absl::StrCat("opening job store ", path, ": ", msg));
  }
  sqlite3_busy_timeout(db, 5000);
  auto store = std::make_unique<SqliteJobStore>(db);
  absl::Status s = store->Init();
  // After Init returned: a statement of Init still stepping would keep the tables locked
  // against the rebuild's DROP TABLE.
  if (s.ok()) s = store->KeyDicomStateBySender();
  if (!s.ok()) return s;
  return std::unique_ptr<JobStore>(std::move(store));
}

absl::StatusOr<std::string> ParseName(const std::string& name, const std::string& collection,
                                      const std::string& field) {
  std::string prefix = collection + "/";
  if (name.size() <= prefix.size() || name.compare(0, prefix.size(), prefix) != 0) {
    return absl::InvalidArgumentError(
        absl::StrCat(field, ": expected '", collection, "/{id}', got '", name, "'"));
  }
  std::string id = name.substr(prefix.size());
  for (char c : id) {
    bool ok = (c >= '0' && c <= '9') || (c >= 'a' && c <= 'z') || c == '-';
    if (!ok) {
      return absl::InvalidArgumentError(
          absl::StrCat(field, ": '", name, "' is not a valid ", collection, " name"));
    }
  }
  return id;
}

}  // namespace decima::server
