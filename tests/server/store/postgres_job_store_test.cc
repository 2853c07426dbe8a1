// What only a shared store must do: several stores (= replicas, each with its own connection
// pool and event feed) on one real PostgreSQL database.
#include <atomic>
#include <map>
#include <mutex>
#include <set>
#include <thread>

#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "tests/server/store/postgres_fixture.h"

namespace decima::server {
namespace {

std::vector<std::unique_ptr<JobStore>> OpenReplicas(const std::string& dsn, int n) {
  std::vector<absl::StatusOr<std::unique_ptr<JobStore>>> opened(n);
  std::vector<std::thread> threads;
  // Together, as replicas of one Deployment start: the migrations must serialize.
  for (int i = 0; i < n; ++i) threads.emplace_back([&, i] { opened[i] = OpenPostgres(dsn); });
  for (auto& t : threads) t.join();
  std::vector<std::unique_ptr<JobStore>> out;
  for (auto& o : opened) {
    EXPECT_TRUE(o.ok()) << o.status();
    if (o.ok()) out.push_back(std::move(*o));
  }
  return out;
}

v1::JobSpec Spec() {
  v1::JobSpec spec;
  spec.set_volume("volumes/v");
  return spec;
}

TEST(PostgresJobStoreTest, ReplicasStartingTogetherApplyTheSchemaOnce) {
  DECIMA_REQUIRE_POSTGRES();
  const std::string dsn = FreshDatabase();
  ASSERT_FALSE(dsn.empty());
  auto stores = OpenReplicas(dsn, 4);
  ASSERT_EQ(stores.size(), 4u);
  const std::string db = dsn.substr(dsn.rfind('/') + 1);
  EXPECT_EQ(
      SharedPostgres()->Sql("SELECT COUNT(*), MAX(version) FROM decima_schema_migrations", db),
      "6|6");  // every migration once (2: creator columns, 3: DICOM receiver tables, 4: keyed
               // by sender, 5: volume content keys, 6: DICOM association ids)
}

// A database at schema version 3, whose receiver tables kept an instance unique by SOP Instance
// UID alone and a series row unique by instance set, upgrades (migration 4) with its rows kept
// and the sender keys in force; its volumes get content keys (migration 5, NULL for the old
// row) and its receiver rows association ids ("" for the old rows, migration 6).
TEST(PostgresJobStoreTest, ReceiverTablesOfVersion3AreKeyedBySenderWithTheirRows) {
  DECIMA_REQUIRE_POSTGRES();
  const std::string dsn = FreshDatabase();
  ASSERT_FALSE(dsn.empty());
  const std::string db = dsn.substr(dsn.rfind('/') + 1);
  // Version 3's receiver tables as migration 3 made them, and its volumes table (the other
  // tables play no part here).
  ASSERT_TRUE(SharedPostgres()->Sql(R"sql(
    CREATE TABLE decima_schema_migrations(
      version INTEGER PRIMARY KEY, applied_at TIMESTAMPTZ NOT NULL DEFAULT now());
    INSERT INTO decima_schema_migrations(version) VALUES (1), (2), (3);
    CREATE TABLE volumes(
      ord BIGSERIAL PRIMARY KEY,
      id TEXT UNIQUE NOT NULL,
      request_id TEXT UNIQUE,
      volume BYTEA NOT NULL,
      creator TEXT NOT NULL DEFAULT '');
    INSERT INTO volumes(id, volume, creator) VALUES ('old', '', 'alice');
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
    INSERT INTO dicom_instances(sop_instance_uid, series_instance_uid, sha256, calling_ae,
                                called_ae, received_ms)
      VALUES ('i1', 's1', 'aa', 'ORTHANC', 'DECIMA', 1);
    INSERT INTO dicom_series VALUES (DEFAULT, 'set-x', 's0', 'jobs/j0', '', 'r', TRUE, '', 3, 3,
                                     'ORTHANC', 'DECIMA', 2, 1, 2);
  )sql",
                                    db));
  auto store = OpenPostgres(dsn);
  ASSERT_TRUE(store.ok()) << store.status();
  EXPECT_EQ(SharedPostgres()->Sql("SELECT MAX(version) FROM decima_schema_migrations", db), "6");
  EXPECT_EQ(SharedPostgres()->Sql("SELECT COUNT(*) FROM volumes WHERE content_key IS NULL", db),
            "1");
  auto instances = (*store)->ListDicomInstances();
  ASSERT_TRUE(instances.ok()) << instances.status();
  ASSERT_EQ(instances->size(), 1u);
  EXPECT_EQ((*instances)[0].size_bytes, 0);
  EXPECT_EQ((*instances)[0].association_id, "");
  ASSERT_TRUE((*store)->PutDicomInstance({"s1", "i1", "bb", "EVIL", "DECIMA", 2, 0, 1, ""}).ok());
  EXPECT_EQ((*store)->ListDicomInstances()->size(), 2u);
  EXPECT_EQ((*store)->PutDicomInstance({"s1", "i1", "bb", "ORTHANC", "DECIMA", 3, 0, 1, ""}).code(),
            absl::StatusCode::kAlreadyExists);
  auto rows = (*store)->ListDicomSeries(true, 10);
  ASSERT_TRUE(rows.ok()) << rows.status();
  ASSERT_EQ(rows->size(), 1u);
  EXPECT_EQ((*rows)[0].receive_key, "set-x");
  EXPECT_EQ((*rows)[0].association_id, "");
  DicomSeriesRecord later = (*rows)[0];
  later.receive_key = "set-x@later";
  ASSERT_TRUE((*store)->PutDicomSeries(later, {}).ok());
  EXPECT_EQ((*store)->ListDicomSeries(false, 10)->size(), 2u);
}

TEST(PostgresJobStoreTest, ConcurrentClaimersTakeEveryJobExactlyOnce) {
  DECIMA_REQUIRE_POSTGRES();
  const std::string dsn = FreshDatabase();
  ASSERT_FALSE(dsn.empty());
  auto stores = OpenReplicas(dsn, 3);
  ASSERT_EQ(stores.size(), 3u);
  constexpr int kJobs = 150;
  for (int i = 0; i < kJobs; ++i) {
    bool created = false;
    ASSERT_TRUE(
        stores[i % 3]->CreateJob("j" + std::to_string(i), Spec(), "", 0, "", &created).ok());
  }
  std::mutex mu;
  std::multiset<std::string> claimed;
  std::vector<std::thread> threads;
  for (int t = 0; t < 6; ++t) {
    threads.emplace_back([&, t] {
      JobStore* s = stores[t % 3].get();
      for (int guard = 0; guard < kJobs * 2; ++guard) {
        auto c = s->ClaimNext("w" + std::to_string(t), 60000);
        ASSERT_TRUE(c.ok()) << c.status();
        if (!c->has_value()) return;
        {
          std::lock_guard<std::mutex> lock(mu);
          claimed.insert((*c)->lease.job_id);
        }
        ASSERT_TRUE(s->Finish((*c)->lease, v1::SUCCEEDED, v1::Job()).ok());
      }
    });
  }
  for (auto& t : threads) t.join();
  EXPECT_EQ(claimed.size(), static_cast<size_t>(kJobs));
  EXPECT_EQ(std::set<std::string>(claimed.begin(), claimed.end()).size(), claimed.size())
      << "a job was claimed twice";
  EXPECT_EQ(*stores[0]->CountJobs(v1::SUCCEEDED), kJobs);
  EXPECT_EQ(*stores[1]->CountJobs(v1::QUEUED), 0);
}

TEST(PostgresJobStoreTest, OneRequestIdFromManyReplicasMakesOneJob) {
  DECIMA_REQUIRE_POSTGRES();
  const std::string dsn = FreshDatabase();
  ASSERT_FALSE(dsn.empty());
  auto stores = OpenReplicas(dsn, 3);
  ASSERT_EQ(stores.size(), 3u);
  std::atomic<int> created_count{0};
  std::mutex mu;
  std::set<std::string> names;
  std::vector<std::thread> threads;
  for (int t = 0; t < 30; ++t) {
    threads.emplace_back([&, t] {
      bool created = false;
      auto j = stores[t % 3]->CreateJob("id" + std::to_string(t), Spec(), "req-1", 0, "", &created);
      ASSERT_TRUE(j.ok()) << j.status();
      if (created) ++created_count;
      std::lock_guard<std::mutex> lock(mu);
      names.insert(j->name());
    });
  }
  for (auto& t : threads) t.join();
  EXPECT_EQ(created_count.load(), 1);
  EXPECT_EQ(names.size(), 1u);
  EXPECT_EQ(*stores[2]->CountJobs(v1::QUEUED), 1);
}

// Events written through replica A reach the listener of replica B complete and in order, also
// across a restart of PostgreSQL (B re-LISTENs and re-reads what it follows).
TEST(PostgresJobStoreTest, EventsReachOtherReplicasInOrderAcrossADatabaseRestart) {
  DECIMA_REQUIRE_POSTGRES();
  const std::string dsn = FreshDatabase();
  ASSERT_FALSE(dsn.empty());
  auto stores = OpenReplicas(dsn, 2);
  ASSERT_EQ(stores.size(), 2u);
  std::mutex mu;
  std::vector<int64_t> seen;
  stores[1]->SetListener([&](const std::string& id, const v1::JobEvent& ev) {
    if (id != "a") return;
    std::lock_guard<std::mutex> lock(mu);
    seen.push_back(ev.sequence());
  });
  auto count = [&] {
    std::lock_guard<std::mutex> lock(mu);
    return seen.size();
  };
  auto wait_for = [&](size_t n) {
    for (int i = 0; i < 1000 && count() < n; ++i) {
      std::this_thread::sleep_for(std::chrono::milliseconds(20));
    }
    return count();
  };
  JobStore& a = *stores[0];
  bool created = false;
  ASSERT_TRUE(a.CreateJob("a", Spec(), "", 0, "", &created).ok());
  auto claim = a.ClaimNext("wa", 60000);
  ASSERT_TRUE(claim.ok() && claim->has_value());
  const Lease lease = (*claim)->lease;
  for (int i = 0; i < 3; ++i) ASSERT_TRUE(a.AppendProgress(lease, v1::Progress()).ok());
  EXPECT_EQ(wait_for(5), 5u);

  SharedPostgres()->Stop();
  ASSERT_EQ(SharedPostgres()->Start(), "");
  // A's pool reconnects inside these calls; B's feed may LISTEN again only after them, so the
  // events reach B through its re-read.
  for (int i = 0; i < 3; ++i) ASSERT_TRUE(a.AppendProgress(lease, v1::Progress()).ok());
  ASSERT_TRUE(a.Finish(lease, v1::SUCCEEDED, v1::Job()).ok());
  EXPECT_EQ(wait_for(9), 9u);
  stores.clear();  // stops the event threads, which use `seen`
  for (size_t i = 0; i < seen.size(); ++i) EXPECT_EQ(seen[i], static_cast<int64_t>(i + 1));
}

}  // namespace
}  // namespace decima::server
