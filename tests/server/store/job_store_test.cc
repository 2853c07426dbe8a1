// The JobStore contract, run against both stores: the embedded SQLite one (server_store_test)
// and PostgreSQL (server_postgres_test, built with DECIMA_JOB_STORE_POSTGRES: a real server in a
// temp folder, one database per test; skipped when PostgreSQL is absent).
#include <atomic>
#include <mutex>
#include <set>
#include <thread>

#include <sqlite3.h>

#include "absl/strings/escaping.h"
#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "server/store/job_store.h"
#include "tests/server/store/dicom_series_record.h"
#include "tests/server/store/postgres_fixture.h"
#include "tests/testing/test_data.h"

namespace decima::server {
namespace {
using ::testing::HasSubstr;

class JobStoreTest : public ::testing::TestWithParam<std::string> {
 protected:
  void SetUp() override {
    if (GetParam() == "postgresql") {
      DECIMA_REQUIRE_POSTGRES();
      path_ = FreshDatabase();
      ASSERT_FALSE(path_.empty());
    } else {
      path_ = (testing::MakeScratchDir("job_store") / "jobs.sqlite").string();
    }
    auto s = Reopen();
    ASSERT_TRUE(s.ok()) << s.status();
    store_ = std::move(*s);
    store_->SetListener([this](const std::string& id, const v1::JobEvent& ev) {
      std::lock_guard<std::mutex> lock(mu_);
      published_.emplace_back(id, ev.sequence());
    });
  }
  // A shared store calls the listener from its own thread until it is destroyed: before the
  // members the listener uses.
  void TearDown() override { store_.reset(); }
  absl::StatusOr<std::unique_ptr<JobStore>> Reopen() {
    return GetParam() == "postgresql" ? OpenPostgres(path_) : OpenSqliteJobStore(path_);
  }
  // The events published so far, once `n` arrived (a shared store delivers them from its
  // event thread) or after 5 s.
  std::vector<std::pair<std::string, int64_t>> Published(size_t n) {
    for (int i = 0; i < 250; ++i) {
      {
        std::lock_guard<std::mutex> lock(mu_);
        if (published_.size() >= n) return published_;
      }
      std::this_thread::sleep_for(std::chrono::milliseconds(20));
    }
    std::lock_guard<std::mutex> lock(mu_);
    return published_;
  }
  v1::Job Create(const std::string& id, const std::string& request_id = "", int max_queued = 100,
                 const std::string& creator = "") {
    v1::JobSpec spec;
    spec.set_volume("volumes/v1");
    bool created = false;
    auto j = store_->CreateJob(id, spec, request_id, max_queued, creator, &created);
    EXPECT_TRUE(j.ok()) << j.status();
    return j.ok() ? *j : v1::Job();
  }
  std::string path_;  // the SQLite file or the PostgreSQL DSN
  std::unique_ptr<JobStore> store_;
  std::mutex mu_;
  std::vector<std::pair<std::string, int64_t>> published_;
};

TEST_P(JobStoreTest, CreateWithSameRequestIdReturnsTheFirstJob) {
  v1::Job a = Create("a", "req-1");
  v1::JobSpec spec;
  bool created = true;
  auto b = store_->CreateJob("b", spec, "req-1", 100, "", &created);
  ASSERT_TRUE(b.ok());
  EXPECT_FALSE(created);
  EXPECT_EQ(b->name(), "jobs/a");
  EXPECT_EQ(*store_->CountJobs(v1::QUEUED), 1);
}

TEST_P(JobStoreTest, FullQueueIsResourceExhausted) {
  Create("a", "", 2);
  Create("b", "", 2);
  v1::JobSpec spec;
  bool created = false;
  auto c = store_->CreateJob("c", spec, "", 2, "", &created);
  EXPECT_EQ(c.status().code(), absl::StatusCode::kResourceExhausted);
}

TEST_P(JobStoreTest, ClaimTakesOldestFirstAndNeverTwice) {
  Create("a");
  Create("b");
  auto x = store_->ClaimNext("w1", 10000);
  auto y = store_->ClaimNext("w2", 10000);
  auto z = store_->ClaimNext("w3", 10000);
  ASSERT_TRUE(x.ok() && y.ok() && z.ok());
  ASSERT_TRUE(x->has_value() && y->has_value());
  EXPECT_EQ((*x)->job.name(), "jobs/a");
  EXPECT_EQ((*y)->job.name(), "jobs/b");
  EXPECT_FALSE(z->has_value());
  EXPECT_EQ((*x)->job.attempts(), 1);
  EXPECT_EQ((*x)->lease.owner, "w1");
  EXPECT_EQ((*x)->lease.epoch, 1);
  // Only the lease holder may report on the job.
  Lease other = (*x)->lease;
  other.owner = "w2";
  EXPECT_EQ(store_->AppendProgress(other, v1::Progress()).code(),
            absl::StatusCode::kFailedPrecondition);
  EXPECT_TRUE(store_->AppendProgress((*x)->lease, v1::Progress()).ok());
}

TEST_P(JobStoreTest, AStaleLeaseIsFencedOffEvenForTheSameOwner) {
  Create("a");
  auto first = store_->ClaimNext("w", -1000);  // lapses at once (a paused replica)
  ASSERT_TRUE(first.ok() && first->has_value());
  ASSERT_TRUE(store_->RecoverLeases(/*all=*/false, 3).ok());
  auto second = store_->ClaimNext("w", 60000);
  ASSERT_TRUE(second.ok() && second->has_value());
  const Lease stale = (*first)->lease, current = (*second)->lease;
  EXPECT_EQ(stale.owner, current.owner);
  EXPECT_EQ(current.epoch, stale.epoch + 1);
  EXPECT_EQ(store_->RenewLease(stale, 60000).code(), absl::StatusCode::kFailedPrecondition);
  EXPECT_EQ(store_->AppendProgress(stale, v1::Progress()).code(),
            absl::StatusCode::kFailedPrecondition);
  EXPECT_EQ(store_->Finish(stale, v1::SUCCEEDED, v1::Job()).status().code(),
            absl::StatusCode::kFailedPrecondition);
  EXPECT_EQ(store_->Requeue(stale, "x").status().code(), absl::StatusCode::kFailedPrecondition);
  EXPECT_EQ(store_->GetJob("a")->state(), v1::RUNNING);
  EXPECT_TRUE(store_->RenewLease(current, 60000).ok());
  auto done = store_->Finish(current, v1::SUCCEEDED, v1::Job());
  ASSERT_TRUE(done.ok()) << done.status();
  EXPECT_EQ(done->attempts(), 2);
  // A finished job's lease is gone for its last holder too.
  EXPECT_EQ(store_->RenewLease(current, 60000).code(), absl::StatusCode::kFailedPrecondition);
}

TEST_P(JobStoreTest, EventsAreGaplessAndPublishedInOrder) {
  Create("a");
  auto claim = store_->ClaimNext("w", 10000);
  ASSERT_TRUE(claim.ok() && claim->has_value());
  const Lease lease = (*claim)->lease;
  for (int i = 0; i < 5; ++i) {
    v1::Progress p;
    p.set_stage("segment");
    p.set_fraction(i / 5.0);
    ASSERT_TRUE(store_->AppendProgress(lease, p).ok());
  }
  v1::Job outcome;
  auto done = store_->Finish(lease, v1::SUCCEEDED, outcome);
  ASSERT_TRUE(done.ok());
  EXPECT_EQ(done->last_sequence(), 8);  // QUEUED, RUNNING, 5 progress, SUCCEEDED
  auto events = store_->ListEvents("a", 0, 100);
  ASSERT_TRUE(events.ok());
  ASSERT_EQ(events->size(), 8u);
  for (size_t i = 0; i < events->size(); ++i) EXPECT_EQ((*events)[i].sequence(), int64_t(i + 1));
  EXPECT_EQ(events->back().state_change().state(), v1::SUCCEEDED);
  const auto published = Published(8);
  std::string order;
  for (const auto& [id, seq] : published) order += id + ":" + std::to_string(seq) + " ";
  ASSERT_EQ(published.size(), 8u) << order;
  for (size_t i = 0; i < published.size(); ++i) EXPECT_EQ(published[i].second, int64_t(i + 1));
  auto tail = store_->ListEvents("a", 6, 100);
  ASSERT_EQ(tail->size(), 2u);
  EXPECT_EQ((*tail)[0].sequence(), 7);
}

TEST_P(JobStoreTest, RecoveryRequeuesRunningJobsThenFailsAfterMaxAttempts) {
  Create("a");
  for (int attempt = 1; attempt <= 2; ++attempt) {
    auto c = store_->ClaimNext("dead-server", 10000);
    ASSERT_TRUE(c.ok() && c->has_value());
    auto r = store_->RecoverLeases(/*all=*/true, /*max_attempts=*/2);
    ASSERT_TRUE(r.ok());
    if (attempt == 1) {
      EXPECT_EQ(r->requeued, std::vector<std::string>{"a"});
      EXPECT_EQ(store_->GetJob("a")->state(), v1::QUEUED);
    } else {
      EXPECT_EQ(r->failed, std::vector<std::string>{"a"});
      EXPECT_EQ(store_->GetJob("a")->state(), v1::FAILED);
      EXPECT_THAT(store_->GetJob("a")->error().message(), HasSubstr("lost 2 times"));
    }
  }
}

TEST_P(JobStoreTest, OnlyLapsedLeasesAreRecoveredWhileServing) {
  Create("a");
  Create("b");
  ASSERT_TRUE(store_->ClaimNext("w", -1000).ok());  // lease already lapsed
  ASSERT_TRUE(store_->ClaimNext("w", 60000).ok());  // lease valid
  auto r = store_->RecoverLeases(/*all=*/false, 3);
  ASSERT_TRUE(r.ok());
  EXPECT_EQ(r->requeued, std::vector<std::string>{"a"});
  EXPECT_EQ(store_->GetJob("b")->state(), v1::RUNNING);
}

TEST_P(JobStoreTest, CancelQueuedIsImmediateCancelRunningIsARequest) {
  Create("a");
  Create("b");
  ASSERT_TRUE(store_->ClaimNext("w", 10000).ok());  // a runs
  auto ca = store_->Cancel("a");
  ASSERT_TRUE(ca.ok());
  EXPECT_EQ(ca->state(), v1::RUNNING);
  EXPECT_TRUE(*store_->CancelRequested("a"));
  auto cb = store_->Cancel("b");
  EXPECT_EQ(cb->state(), v1::CANCELLED);
  EXPECT_EQ(store_->Retry("a", 100).status().code(), absl::StatusCode::kFailedPrecondition);
  auto rb = store_->Retry("b", 100);
  ASSERT_TRUE(rb.ok());
  EXPECT_EQ(rb->state(), v1::QUEUED);
  EXPECT_EQ(store_->Cancel("zzz").status().code(), absl::StatusCode::kNotFound);
}

TEST_P(JobStoreTest, ListPagesNewestFirstWithStateFilterAndRejectsForeignTokens) {
  for (int i = 0; i < 7; ++i) Create("j" + std::to_string(i));
  ASSERT_TRUE(store_->ClaimNext("w", 10000).ok());  // j0 RUNNING
  std::vector<std::string> names;
  std::string token;
  do {
    auto page = store_->ListJobs({}, "", 3, token);
    ASSERT_TRUE(page.ok());
    EXPECT_LE(page->jobs.size(), 3u);
    for (auto& j : page->jobs) names.push_back(j.name());
    token = page->next_page_token;
  } while (!token.empty());
  ASSERT_EQ(names.size(), 7u);
  EXPECT_EQ(names.front(), "jobs/j6");
  EXPECT_EQ(names.back(), "jobs/j0");
  auto running = store_->ListJobs({v1::RUNNING}, "", 10, "");
  ASSERT_EQ(running->jobs.size(), 1u);
  EXPECT_EQ(running->jobs[0].name(), "jobs/j0");
  EXPECT_EQ(store_->ListJobs({}, "", 3, "garbage").status().code(),
            absl::StatusCode::kInvalidArgument);
}

TEST_P(JobStoreTest, CreatorIsStoredAndFiltersListingsPageByPage) {
  for (int i = 0; i < 5; ++i) Create("a" + std::to_string(i), "", 100, "alice");
  Create("b0", "", 100, "bob");
  EXPECT_EQ(store_->GetJob("b0")->creator(), "bob");
  std::vector<std::string> names;
  std::string token;
  int pages = 0;
  do {
    auto page = store_->ListJobs({}, "alice", 2, token);
    ASSERT_TRUE(page.ok()) << page.status();
    for (auto& j : page->jobs) {
      EXPECT_EQ(j.creator(), "alice");
      names.push_back(j.name());
    }
    token = page->next_page_token;
  } while (!token.empty() && ++pages < 10);
  EXPECT_EQ(names.size(), 5u);
  EXPECT_EQ(store_->ListJobs({}, "", 100, "")->jobs.size(), 6u);
  EXPECT_EQ(store_->ListJobs({v1::QUEUED}, "bob", 100, "")->jobs.size(), 1u);
  EXPECT_TRUE(store_->ListJobs({}, "carol", 100, "")->jobs.empty());

  v1::Volume v;
  v.set_creator("bob");
  bool created = false;
  ASSERT_TRUE(store_->CreateVolume("vb", v, "", "", &created).ok());
  v.set_creator("alice");
  ASSERT_TRUE(store_->CreateVolume("va", v, "", "", &created).ok());
  auto bobs = store_->ListVolumes("bob", 10, "");
  ASSERT_TRUE(bobs.ok());
  ASSERT_EQ(bobs->volumes.size(), 1u);
  EXPECT_EQ(bobs->volumes[0].creator(), "bob");
  EXPECT_EQ(store_->ListVolumes("", 10, "")->volumes.size(), 2u);
}

TEST_P(JobStoreTest, JobsSurviveReopening) {
  Create("a");
  store_.reset();
  auto s = Reopen();
  ASSERT_TRUE(s.ok());
  auto j = (*s)->GetJob("a");
  ASSERT_TRUE(j.ok());
  EXPECT_EQ(j->state(), v1::QUEUED);
}

TEST_P(JobStoreTest, VolumeInUseCannotBeDeleted) {
  v1::Volume v;
  v.add_files()->set_blob("blobs/" + std::string(64, 'a'));
  bool created = false;
  ASSERT_TRUE(store_->CreateVolume("v1", v, "", "", &created).ok());
  EXPECT_TRUE(*store_->BlobInUse(std::string(64, 'a')));
  Create("a");  // reads volumes/v1
  EXPECT_EQ(store_->DeleteVolume("v1").code(), absl::StatusCode::kFailedPrecondition);
  ASSERT_TRUE(store_->Cancel("a").ok());
  EXPECT_TRUE(store_->DeleteVolume("v1").ok());
  EXPECT_FALSE(*store_->BlobInUse(std::string(64, 'a')));
  EXPECT_EQ(store_->GetVolume("v1").status().code(), absl::StatusCode::kNotFound);
}

TEST_P(JobStoreTest, LabelMapOfAQueuedJobCannotBeDeleted) {
  bool created = false;
  for (const char* id : {"v1", "labels"}) {
    v1::Volume v;
    v.add_files()->set_blob("blobs/" + std::string(64, id[0]));
    ASSERT_TRUE(store_->CreateVolume(id, v, "", "", &created).ok());
  }
  v1::JobSpec spec;
  spec.set_volume("volumes/v1");
  spec.set_label_map("volumes/labels");
  ASSERT_TRUE(store_->CreateJob("a", spec, "", 100, "", &created).ok());
  const absl::Status st = store_->DeleteVolume("labels");
  EXPECT_EQ(st.code(), absl::StatusCode::kFailedPrecondition) << st;
  EXPECT_THAT(std::string(st.message()), HasSubstr("label map"));
  ASSERT_TRUE(store_->Cancel("a").ok());
  EXPECT_TRUE(store_->DeleteVolume("labels").ok());
}

// CreateVolume by content (issue 35 part 7): the same creator and key answer the first row,
// another creator's key is another row, a deleted volume is not answered again, and the key
// survives reopening the store.
TEST_P(JobStoreTest, AVolumeFileThatNamesNoBlobIsRefusedAndNothingIsKept) {
  v1::Volume v;
  v.add_files()->set_path("a.nii");
  v.set_creator("alice");
  for (const std::string blob : {"", "blob", "files/x"}) {
    v.mutable_files(0)->set_blob(blob);
    bool created = true;
    auto made = store_->CreateVolume("vbad", v, "", "", &created);
    EXPECT_EQ(made.status().code(), absl::StatusCode::kInvalidArgument) << "'" << blob << "'";
    EXPECT_THAT(std::string(made.status().message()), HasSubstr("a.nii"));
    EXPECT_FALSE(created);
    EXPECT_EQ(store_->GetVolume("vbad").status().code(), absl::StatusCode::kNotFound);
  }
}

TEST_P(JobStoreTest, VolumesAreFoundByCreatorAndContentKeyUntilDeleted) {
  const std::string key(64, 'c');
  v1::Volume v;
  v.add_files()->set_blob("blobs/" + std::string(64, 'a'));
  v.set_creator("alice");
  v.set_display_name("first");
  bool created = false;
  ASSERT_TRUE(store_->CreateVolume("v1", v, "", key, &created).ok());
  EXPECT_TRUE(created);
  v.set_name("volumes/ignored");
  v.set_display_name("second");
  auto again = store_->CreateVolume("v2", v, "", key, &created);
  ASSERT_TRUE(again.ok()) << again.status();
  EXPECT_FALSE(created);
  EXPECT_EQ(again->display_name(), "first");
  EXPECT_EQ(store_->GetVolume("v2").status().code(), absl::StatusCode::kNotFound);

  v.set_creator("bob");
  auto bobs = store_->CreateVolume("v3", v, "", key, &created);
  ASSERT_TRUE(bobs.ok()) << bobs.status();
  EXPECT_TRUE(created);
  EXPECT_EQ(bobs->display_name(), "second");

  // Without a key (a store's own callers, rows from before keys): never found by content.
  ASSERT_TRUE(store_->CreateVolume("v4", v, "", "", &created).ok());
  EXPECT_TRUE(created);
  ASSERT_TRUE(store_->CreateVolume("v5", v, "", "", &created).ok());
  EXPECT_TRUE(created);

  store_.reset();
  auto reopened = Reopen();
  ASSERT_TRUE(reopened.ok()) << reopened.status();
  store_ = std::move(*reopened);
  v.set_creator("alice");
  auto after = store_->CreateVolume("v6", v, "", key, &created);
  ASSERT_TRUE(after.ok());
  EXPECT_FALSE(created);
  EXPECT_EQ(store_->GetVolume("v1")->display_name(), "first");
  ASSERT_TRUE(store_->DeleteVolume("v1").ok());
  auto fresh = store_->CreateVolume("v7", v, "", key, &created);
  ASSERT_TRUE(fresh.ok()) << fresh.status();
  EXPECT_TRUE(created);
  EXPECT_TRUE(store_->GetVolume("v7").ok());
  EXPECT_EQ(store_->ListVolumes("alice", 10, "")->volumes.size(), 1u);
  EXPECT_EQ(store_->ListVolumes("bob", 10, "")->volumes.size(), 3u);
}

// The DICOM receiver's state (dicom_receiver.h): received instances, the persisted abort mark
// and the receives' outcomes survive a restart; a check consumes its sender's instances in one
// step, and every receive keeps its own row.
TEST_P(JobStoreTest, DicomReceiverStateSurvivesReopeningAndAJobConsumesItsInstances) {
  const std::string aa(64, 'a'), bb(64, 'b');
  ASSERT_TRUE(
      store_->PutDicomInstance({"s1", "i1", aa, "ORTHANC", "DECIMA", 1, 0, 10, "assoc-1"}).ok());
  ASSERT_TRUE(
      store_->PutDicomInstance({"s1", "i2", bb, "ORTHANC", "DECIMA", 2, 0, 20, "assoc-1"}).ok());
  ASSERT_TRUE(store_->PutDicomInstance({"s2", "k1", bb, "OTHER", "DECIMA", 2, 0, 20, "x"}).ok());
  // The same SOP instance with the same bytes again replaces its row and moves to the end, with
  // the association that brought it this time.
  ASSERT_TRUE(
      store_->PutDicomInstance({"s1", "i1", aa, "ORTHANC", "DECIMA", 3, 0, 10, "assoc-2"}).ok());
  ASSERT_TRUE(store_->MarkDicomSeriesAborted("ORTHANC", "s1", 4).ok());
  EXPECT_TRUE(*store_->BlobInUse(aa));
  EXPECT_FALSE(*store_->BlobInUse(std::string(64, 'c')));
  DicomSeriesRecord incomplete =
      Check("set-a", "s1", "", "incomplete: 1 slice(s) missing", v1::ReceivedSeries::INCOMPLETE);
  incomplete.calling_ae = "ORTHANC";
  incomplete.called_ae = "DECIMA";
  incomplete.instance_count = 2;
  incomplete.first_received_ms = 2;
  incomplete.last_received_ms = 3;
  incomplete.association_id = "assoc-2";
  ASSERT_TRUE(store_->PutDicomSeries(incomplete, {}).ok());

  store_.reset();  // a restart
  auto reopened = Reopen();
  ASSERT_TRUE(reopened.ok()) << reopened.status();
  store_ = std::move(*reopened);
  auto instances = store_->ListDicomInstances();
  ASSERT_TRUE(instances.ok()) << instances.status();
  ASSERT_EQ(instances->size(), 3u);
  EXPECT_EQ((*instances)[0].sop_instance_uid, "i2");  // arrival order, i1 re-sent last
  EXPECT_EQ((*instances)[0].aborted_ms, 4);
  EXPECT_EQ((*instances)[0].size_bytes, 20);
  EXPECT_EQ((*instances)[0].association_id, "assoc-1");
  EXPECT_EQ((*instances)[2].association_id, "assoc-2");
  EXPECT_EQ((*instances)[1].aborted_ms, 0);  // another series
  EXPECT_EQ((*instances)[2].sop_instance_uid, "i1");
  EXPECT_EQ((*instances)[2].received_ms, 3);
  EXPECT_EQ((*instances)[2].aborted_ms, 4);
  auto checks = store_->ListDicomSeries(false, 10);
  ASSERT_TRUE(checks.ok()) << checks.status();
  ASSERT_EQ(checks->size(), 1u);
  const DicomSeriesRecord& c = (*checks)[0];
  EXPECT_EQ(c.receive_key, "set-a@r");
  EXPECT_EQ(c.state, v1::ReceivedSeries::INCOMPLETE);
  EXPECT_EQ(c.reason, "incomplete: 1 slice(s) missing");
  EXPECT_EQ(c.calling_ae, "ORTHANC");
  EXPECT_EQ(c.called_ae, "DECIMA");
  EXPECT_EQ(c.instance_count, 2);
  EXPECT_EQ(c.first_received_ms, 2);
  EXPECT_EQ(c.last_received_ms, 3);
  EXPECT_EQ(c.association_id, "assoc-2");

  DicomSeriesRecord queued = Check("set-b", "s1", "jobs/j1", "", v1::ReceivedSeries::QUEUED);
  queued.calling_ae = "ORTHANC";
  queued.results_pending = true;
  ASSERT_TRUE(store_->PutDicomSeries(queued, {"i1", "i2"}).ok());
  ASSERT_EQ(store_->ListDicomInstances()->size(), 1u);  // s2's only
  EXPECT_FALSE(*store_->BlobInUse(aa));
  EXPECT_TRUE(*store_->BlobInUse(bb));  // still held by s2's instance
  auto pending = store_->ListDicomSeries(true, 10);
  ASSERT_TRUE(pending.ok());
  ASSERT_EQ(pending->size(), 1u);
  EXPECT_EQ((*pending)[0].job, "jobs/j1");
  queued.results_pending = false;
  queued.state = v1::ReceivedSeries::SENT;
  queued.send_status = "sent: 3 instances";
  ASSERT_TRUE(store_->PutDicomSeries(queued, {}).ok());
  EXPECT_TRUE(store_->ListDicomSeries(true, 10)->empty());
  // The same set sent again later is another receive: a row of its own, the first one kept.
  DicomSeriesRecord again = queued;
  again.receive_key = "set-b@later";
  again.association_id = "assoc-3";
  again.state = v1::ReceivedSeries::QUEUED;
  again.send_status.clear();
  ASSERT_TRUE(store_->PutDicomSeries(again, {}).ok());
  auto all = store_->ListDicomSeries(false, 10);
  ASSERT_EQ(all->size(), 3u);
  EXPECT_EQ((*all)[0].receive_key, "set-b@later");  // newest first
  EXPECT_EQ((*all)[0].association_id, "assoc-3");
  EXPECT_EQ((*all)[1].association_id, "");
  EXPECT_EQ((*all)[1].send_status, "sent: 3 instances");
  EXPECT_EQ((*all)[1].state, v1::ReceivedSeries::SENT);
  EXPECT_EQ((*all)[2].reason, "incomplete: 1 slice(s) missing");
  EXPECT_EQ(store_->ListDicomSeries(false, 1)->size(), 1u);
}

// Received instances are keyed by sender: another calling AE title's instance with the same SOP
// Instance UID is its own row (it neither replaces nor consumes the first sender's), and the
// same sender's instance with other bytes is refused, the first bytes kept.
TEST_P(JobStoreTest, DicomInstancesAreKeptPerSenderAndOtherBytesAreRefused) {
  const std::string aa(64, 'a'), bb(64, 'b');
  ASSERT_TRUE(store_->PutDicomInstance({"s1", "i1", aa, "ORTHANC", "DECIMA", 1, 0, 100, ""}).ok());
  ASSERT_TRUE(store_->PutDicomInstance({"s1", "i2", aa, "ORTHANC", "DECIMA", 2, 0, 100, ""}).ok());
  ASSERT_TRUE(store_->PutDicomInstance({"s1", "i1", bb, "EVIL", "DECIMA", 3, 0, 7, ""}).ok());
  const absl::Status replaced =
      store_->PutDicomInstance({"s1", "i1", bb, "ORTHANC", "DECIMA", 4, 0, 7, ""});
  EXPECT_EQ(replaced.code(), absl::StatusCode::kAlreadyExists) << replaced;
  EXPECT_THAT(std::string(replaced.message()), HasSubstr("i1"));
  auto instances = store_->ListDicomInstances();
  ASSERT_TRUE(instances.ok()) << instances.status();
  ASSERT_EQ(instances->size(), 3u);
  EXPECT_EQ((*instances)[0].sha256, aa);  // ORTHANC's i1 unchanged
  EXPECT_EQ((*instances)[0].received_ms, 1);
  EXPECT_EQ((*instances)[2].calling_ae, "EVIL");
  EXPECT_EQ(*store_->DicomWaitingBytes("ORTHANC"), 200);
  EXPECT_EQ(*store_->DicomWaitingBytes("EVIL"), 7);
  EXPECT_EQ(*store_->DicomWaitingBytes("NOBODY"), 0);
  // An abort of EVIL's association marks EVIL's instances only.
  ASSERT_TRUE(store_->MarkDicomSeriesAborted("EVIL", "s1", 9).ok());
  instances = store_->ListDicomInstances();
  EXPECT_EQ((*instances)[0].aborted_ms, 0);
  EXPECT_EQ((*instances)[2].aborted_ms, 9);
  // EVIL's series consumed: ORTHANC's instances of the same SOP Instance UID stay.
  DicomSeriesRecord evil = Check("set-e", "s1", "jobs/e", "", v1::ReceivedSeries::QUEUED);
  evil.calling_ae = "EVIL";
  ASSERT_TRUE(store_->PutDicomSeries(evil, {"i1"}).ok());
  ASSERT_EQ(store_->ListDicomInstances()->size(), 2u);
  EXPECT_TRUE(*store_->BlobInUse(aa));
  EXPECT_FALSE(*store_->BlobInUse(bb));
  // Removed (expiry, delete): the sender's series only, returned for their blobs.
  ASSERT_TRUE(store_->PutDicomInstance({"s1", "i3", bb, "EVIL", "DECIMA", 5, 0, 7, ""}).ok());
  auto removed = store_->RemoveDicomInstances("ORTHANC", "s1");
  ASSERT_TRUE(removed.ok()) << removed.status();
  ASSERT_EQ(removed->size(), 2u);
  EXPECT_EQ((*removed)[0].sop_instance_uid, "i1");
  EXPECT_EQ((*removed)[1].sha256, aa);
  instances = store_->ListDicomInstances();
  ASSERT_EQ(instances->size(), 1u);
  EXPECT_EQ((*instances)[0].calling_ae, "EVIL");
  EXPECT_FALSE(*store_->BlobInUse(aa));
  EXPECT_EQ(*store_->DicomWaitingBytes("ORTHANC"), 0);
  EXPECT_TRUE(store_->RemoveDicomInstances("ORTHANC", "s1")->empty());
}

TEST_P(JobStoreTest, CompactGivesDeletedJobsSpaceBack) {
  if (GetParam() != "sqlite")
    GTEST_SKIP() << "file compaction is SQLite's (PostgreSQL autovacuums)";
  std::vector<std::string> ids;
  for (int i = 0; i < 300; ++i) {
    ids.push_back("j" + std::to_string(i));
    Create(ids.back(), "", 1000);
  }
  ASSERT_TRUE(store_->Compact().ok());
  const auto main_file = [&] { return std::filesystem::file_size(path_); };
  for (const auto& id : ids) {
    ASSERT_TRUE(store_->Cancel(id).ok());
    ASSERT_TRUE(store_->DeleteJob(id).ok());
  }
  store_.reset();  // checkpoint on close
  const auto full = main_file();
  auto s = OpenSqliteJobStore(path_);
  ASSERT_TRUE(s.ok());
  store_ = std::move(*s);
  ASSERT_TRUE(store_->Compact().ok());
  store_.reset();
  // Back to (about) the size of an empty store.
  const std::string empty = (testing::MakeScratchDir("empty_store") / "jobs.sqlite").string();
  ASSERT_TRUE(OpenSqliteJobStore(empty).ok());
  const auto empty_size = std::filesystem::file_size(empty);
  EXPECT_LT(main_file(), full);
  EXPECT_LE(main_file(), empty_size + 8192) << "before " << full << " after " << main_file();
}

#ifndef DECIMA_JOB_STORE_POSTGRES
// A data dir whose receiver tables predate keying by sender (an instance unique by SOP Instance
// UID alone, a series row unique by instance set) opens with its rows kept and the new keys in
// force: another sender's instance of the same SOP Instance UID is its own row, and a later
// receive of the same set gets its own row.
// A data dir from before volumes had content keys: the column is added, the old row stays (and
// is not found by content), and new volumes are found by content from then on.
TEST(SqliteJobStoreMigrationTest, VolumesFromBeforeContentKeysKeepTheirRows) {
  const auto path = (testing::MakeScratchDir("volume_migration") / "jobs.sqlite").string();
  sqlite3* db = nullptr;
  ASSERT_EQ(sqlite3_open(path.c_str(), &db), SQLITE_OK);
  v1::Volume old;
  old.set_name("volumes/old");
  old.set_creator("alice");
  const std::string bytes = old.SerializeAsString();
  const std::string kBefore = R"sql(
    CREATE TABLE volumes(
      ord INTEGER PRIMARY KEY AUTOINCREMENT,
      id TEXT UNIQUE NOT NULL,
      request_id TEXT UNIQUE,
      volume BLOB NOT NULL,
      creator TEXT NOT NULL DEFAULT '');
    INSERT INTO volumes(id, volume, creator) VALUES('old', X')sql" +
                              absl::BytesToHexString(bytes) + R"sql(', 'alice');
  )sql";
  ASSERT_EQ(sqlite3_exec(db, kBefore.c_str(), nullptr, nullptr, nullptr), SQLITE_OK)
      << sqlite3_errmsg(db);
  sqlite3_close(db);

  auto store = OpenSqliteJobStore(path);
  ASSERT_TRUE(store.ok()) << store.status();
  EXPECT_EQ((*store)->GetVolume("old")->name(), "volumes/old");
  bool created = false;
  const std::string key(64, 'd');
  ASSERT_TRUE((*store)->CreateVolume("new", old, "", key, &created).ok());
  EXPECT_TRUE(created);
  auto again = (*store)->CreateVolume("newer", old, "", key, &created);
  ASSERT_TRUE(again.ok()) << again.status();
  EXPECT_FALSE(created);
  EXPECT_EQ((*store)->ListVolumes("alice", 10, "")->volumes.size(), 2u);
}

TEST(SqliteJobStoreMigrationTest, ReceiverTablesFromBeforeSenderKeysAreUpgradedWithTheirRows) {
  const auto path = (testing::MakeScratchDir("dicom_migration") / "jobs.sqlite").string();
  sqlite3* db = nullptr;
  ASSERT_EQ(sqlite3_open(path.c_str(), &db), SQLITE_OK);
  const char* kBefore = R"sql(
    CREATE TABLE dicom_instances(
      ord INTEGER PRIMARY KEY AUTOINCREMENT,
      sop_instance_uid TEXT UNIQUE NOT NULL,
      series_instance_uid TEXT NOT NULL,
      sha256 TEXT NOT NULL,
      calling_ae TEXT NOT NULL, called_ae TEXT NOT NULL,
      received_ms INTEGER NOT NULL,
      aborted_ms INTEGER NOT NULL DEFAULT 0);
    CREATE INDEX dicom_instances_by_sha ON dicom_instances(sha256);
    CREATE TABLE dicom_series(
      ord INTEGER PRIMARY KEY AUTOINCREMENT,
      instance_set TEXT UNIQUE NOT NULL,
      series_instance_uid TEXT NOT NULL,
      job TEXT NOT NULL, reason TEXT NOT NULL, route TEXT NOT NULL,
      results_pending INTEGER NOT NULL, send_status TEXT NOT NULL,
      update_ms INTEGER NOT NULL,
      state INTEGER NOT NULL DEFAULT 0,
      calling_ae TEXT NOT NULL DEFAULT '', called_ae TEXT NOT NULL DEFAULT '',
      instance_count INTEGER NOT NULL DEFAULT 0,
      first_received_ms INTEGER NOT NULL DEFAULT 0,
      last_received_ms INTEGER NOT NULL DEFAULT 0);
    INSERT INTO dicom_instances(sop_instance_uid, series_instance_uid, sha256, calling_ae,
                                called_ae, received_ms, aborted_ms)
      VALUES('i1', 's1', 'aa', 'ORTHANC', 'DECIMA', 1, 0), ('i2', 's1', 'bb', 'ORTHANC', 'DECIMA', 2, 5);
    INSERT INTO dicom_series(instance_set, series_instance_uid, job, reason, route,
                             results_pending, send_status, update_ms, state, calling_ae)
      VALUES('set-x', 's0', 'jobs/j0', '', 'r', 1, '', 3, 3, 'ORTHANC');
  )sql";
  ASSERT_EQ(sqlite3_exec(db, kBefore, nullptr, nullptr, nullptr), SQLITE_OK) << sqlite3_errmsg(db);
  sqlite3_close(db);

  auto store = OpenSqliteJobStore(path);
  ASSERT_TRUE(store.ok()) << store.status();
  auto instances = (*store)->ListDicomInstances();
  ASSERT_TRUE(instances.ok()) << instances.status();
  ASSERT_EQ(instances->size(), 2u);
  EXPECT_EQ((*instances)[1].sop_instance_uid, "i2");
  EXPECT_EQ((*instances)[1].aborted_ms, 5);
  EXPECT_EQ((*instances)[1].association_id, "");  // the column added after the rebuild
  EXPECT_TRUE(*(*store)->BlobInUse("bb"));
  ASSERT_TRUE((*store)->PutDicomInstance({"s1", "i1", "cc", "EVIL", "DECIMA", 9, 0, 1, ""}).ok());
  EXPECT_EQ((*store)->ListDicomInstances()->size(), 3u);
  EXPECT_EQ((*store)->PutDicomInstance({"s1", "i1", "cc", "ORTHANC", "DECIMA", 9, 0, 1, ""}).code(),
            absl::StatusCode::kAlreadyExists);
  auto rows = (*store)->ListDicomSeries(true, 10);
  ASSERT_TRUE(rows.ok()) << rows.status();
  ASSERT_EQ(rows->size(), 1u);
  EXPECT_EQ((*rows)[0].receive_key, "set-x");
  EXPECT_EQ((*rows)[0].job, "jobs/j0");
  DicomSeriesRecord later = (*rows)[0];
  later.receive_key = "set-x@later";
  ASSERT_TRUE((*store)->PutDicomSeries(later, {}).ok());
  EXPECT_EQ((*store)->ListDicomSeries(false, 10)->size(), 2u);
  store->reset();
  ASSERT_TRUE(OpenSqliteJobStore(path).ok());  // and opens again as it is
}
#endif

#ifdef DECIMA_JOB_STORE_POSTGRES
INSTANTIATE_TEST_SUITE_P(Stores, JobStoreTest, ::testing::Values("postgresql"),
                         [](const auto& info) { return info.param; });
#else
INSTANTIATE_TEST_SUITE_P(Stores, JobStoreTest, ::testing::Values("sqlite"),
                         [](const auto& info) { return info.param; });
#endif

TEST(ParseNameTest, AcceptsOnlyTheCollectionAndSafeIds) {
  EXPECT_EQ(*ParseName("jobs/ab12", "jobs", "name"), "ab12");
  EXPECT_FALSE(ParseName("jobs/", "jobs", "name").ok());
  EXPECT_FALSE(ParseName("volumes/ab", "jobs", "name").ok());
  EXPECT_FALSE(ParseName("jobs/../x", "jobs", "name").ok());
  EXPECT_THAT(std::string(ParseName("x", "jobs", "spec.volume").status().message()),
              HasSubstr("spec.volume"));
}

}  // namespace
}  // namespace decima::server
